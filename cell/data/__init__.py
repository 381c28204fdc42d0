"""Data the cell records and learns from: motion datasets, samples for fitting, run recordings, and
the excitation motion generators."""
