"""Corner cases: the recorder that opens a case around each event, the windows cut from
``run.mcap`` after the run, and ``hil cases``/``hil replay`` (what a replay can bring back, and
whether a received run folder's target may be started)."""
