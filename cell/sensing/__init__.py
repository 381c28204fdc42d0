"""What the cell knows of forces: external-torque observers, derivatives, the wrench map, the virtual
force sensor, the F/T sensor as a force source and the tool's gravity on it."""
