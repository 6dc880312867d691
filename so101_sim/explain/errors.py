"""The one error `so101-sim explain` reports as a one-line message (no torch needed)."""


class ExplainError(ValueError):
    """The dataset, episode, frame, k or checkpoint cannot be explained."""
