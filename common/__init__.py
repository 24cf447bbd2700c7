"""The shared vocabulary every package of ours may import: a leaf that imports nothing
of ours. ``errors``: the exception tree; ``classes``: the object classes."""
