"""The control step's parts: the fixed-period loop, the impedance law, the safety limits, signals,
motion primitives and guarded-motion speeds."""
