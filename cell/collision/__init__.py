"""Contact safety: the geometric checker (arm against itself and the fixtures), the collision detector
on the hybrid model, and the guard that reacts to it in the loop."""
