"""What people and other programs see of a run: PNG plots, the UDP wrench publisher and the Rerun
recording and view."""
