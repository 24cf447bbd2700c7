"""``python -m targets.cnn``: serve the CNN target (see ``targets.cnn.target``)."""

from targets.cnn.target import main

if __name__ == "__main__":
    raise SystemExit(main())
