"""Demonstrations from files: LeRobot datasets (v2.1, v3.0) and Minari datasets, offline.

Readers return :class:`LoadedDemonstrations` whose ``rows`` extend a
:class:`~imitrl.data.DemonstrationBuffer`; :func:`save_lerobot` writes a buffer
(every DAgger round included) as a LeRobot v3.0 dataset. Needs the ``datasets``
extra (pyarrow; h5py for Minari). The network is used only to download a LeRobot
``repo_id`` no local cache holds (:func:`download_lerobot`, the ``hub`` extra; not with
``HF_HUB_OFFLINE=1``).
"""

from imitrl.datasets._common import EnvMismatchError, LoadedDemonstrations
from imitrl.datasets.lerobot import (
    DEFAULT_KEY_MAP,
    IMITRL_COLUMNS,
    HubLimits,
    download_lerobot,
    load_lerobot,
    resolve_lerobot_root,
    save_dagger_lerobot,
    save_lerobot,
    save_metaworld_lerobot,
)
from imitrl.datasets.minari import load_minari, resolve_minari_root, save_minari

__all__ = [
    "DEFAULT_KEY_MAP",
    "IMITRL_COLUMNS",
    "EnvMismatchError",
    "HubLimits",
    "LoadedDemonstrations",
    "download_lerobot",
    "load_lerobot",
    "load_minari",
    "resolve_lerobot_root",
    "resolve_minari_root",
    "save_dagger_lerobot",
    "save_lerobot",
    "save_metaworld_lerobot",
    "save_minari",
]
