"""Training the paper's CNN target on simulator-rendered data: ``hil train`` and the
dataset it renders. Imports scenarios (ground-truth boxes) and targets (the model);
the target itself never sees this package."""
