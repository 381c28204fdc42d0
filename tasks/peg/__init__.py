"""Sensorless peg-in-hole (paper 6.2): the task's state machine and its phases (survey, touch,
search, bore, compliance, twist), settings and scoring."""
