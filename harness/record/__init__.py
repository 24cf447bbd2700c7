"""What a run leaves behind: the MCAP recorder and its channels, Foxglove output and layout,
the live view, and the run folder (claiming it, reading it back)."""
