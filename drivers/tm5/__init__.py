"""The TM5-700 arm over its network channels: the Modbus register map, the user-area contract with
the robot-side program, and the driver."""
