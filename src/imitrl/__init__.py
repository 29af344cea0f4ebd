"""imitrl: imitation learning on TorchRL, checked against exact tabular ground truth."""

__version__ = "0.1.0"
