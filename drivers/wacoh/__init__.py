"""The WACOH WEF-6A200-4-RCD (DynPick) F/T sensor over serial: settings, the wire codec and the
driver."""
