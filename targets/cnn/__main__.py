"""``python -m hil.targets.cnn``: serve the CNN target (see ``hil.targets.cnn.target``)."""

from hil.targets.cnn.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
