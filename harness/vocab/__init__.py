"""The harness's vocabulary, its bottom floor: the event model and bus, the observer
protocols and the verdict every room above speaks."""
