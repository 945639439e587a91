"""Photo-consistent refinement of the network maps and the per-image lights (issue 16)."""
