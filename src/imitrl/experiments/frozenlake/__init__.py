"""The section's FrozenLake study: `imitrl frozenlake`.

Each name is imported from its module on first use (PEP 562): the config (numpy and
gymnasium only) without the study's pipeline, so ``imitrl frozenlake --help`` starts
without torch.
"""

from imitrl import _lazy_exports

__all__ = ["PROTOCOLS", "StudyConfig", "run_study"]

__getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "PROTOCOLS": "imitrl.experiments.frozenlake.config",
        "StudyConfig": "imitrl.experiments.frozenlake.config",
        "run_study": "imitrl.experiments.frozenlake.study",
    },
)
