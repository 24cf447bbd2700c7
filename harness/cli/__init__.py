"""The command line: ``hil``'s entry point, the progress display, ``hil clock``, and the
pytest plugin (``hil_run`` fixture) for users' own latency tests."""
