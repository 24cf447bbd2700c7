"""The seed paper's example AI: an object-detector CNN, a steering CNN, object
positions from the boxes (pinhole model, size priors), SAFE/SLOW/STOP decisions and
control, composed modularly and served through the target SDK.

- ``models``      the two nets (torch), decoding, loading the shipped weights
- ``preprocess``  what each net sees of a frame (numpy + OpenCV)
- ``geometry``    position from a box
- ``decision``    in-path test, low-confidence overrides, the baseline's rules
- ``commands``    model swaps and status over the transport
- ``target``      ``CnnTarget.infer`` and ``main`` (``python -m hil.targets.cnn``)

Training lives in the harness (``hil train``, ``training/train.py``,
``training/dataset.py``): this package never sees the simulator or ground truth.
"""
