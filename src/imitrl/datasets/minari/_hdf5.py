"""Minari's ``hdf5`` storage (``minari/dataset/_storages/hdf5_storage.py``, Minari 0.5)::

    <dataset>/data/main_data.hdf5   one group per episode, "episode_<id>", attrs id, seed,
                                    total_steps; datasets observations [T+1, ...] (a group per
                                    Dict key, "_index_<i>" per Tuple entry), actions [T, ...],
                                    rewards [T], terminations [T], truncations [T], infos/...

(Minari < 0.5 kept the dataset's metadata in the file's root attributes: read too.)

Everything is reached through hard links (:func:`node`): HDF5 can also name data in
other files (external links, virtual datasets, external raw storage), which would make
a downloaded file read outside its folder, and Minari writes none of them: each is
refused by name.

The file is opened once, by the descriptor its folder gave (:func:`open_hdf5`), and every
dataset's declared size is checked against the bytes it stores before it is read, and
what the file's datasets declare beyond them against the load's floor, all together
(:func:`read_dataset`, :mod:`._bounds`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np

from imitrl.datasets.minari._bounds import Floor, check_declared
from imitrl.datasets.minari._episodes import EpisodeList, Steps, as_count, list_episodes
from imitrl.datasets.minari._spaces import decode
from imitrl.fs.reading import fd_path

__all__ = [
    "MAIN_FILE",
    "attrs_metadata",
    "list_groups",
    "open_hdf5",
    "read_dataset",
    "read_group",
]

MAIN_FILE = "main_data.hdf5"
_FIELDS = ("observations", "actions", "rewards", "terminations", "truncations")


def node(group: Any, name: str, where: str) -> Any:
    """``group[name]``, reached through a hard link, and when it is a dataset, one whose
    values are stored in this file; ValueError naming it otherwise (see the module
    docstring)."""
    import h5py

    link = group.get(name, getlink=True)
    if link is None:
        raise ValueError(f"{where} is missing")
    if not isinstance(link, h5py.HardLink):
        kind = type(link).__name__
        raise ValueError(
            f"{where} is an HDF5 {kind} (to {getattr(link, 'filename', '')}"
            f"{getattr(link, 'path', '')}); a Minari file holds its data itself, and a "
            "downloaded file never makes this loader read another"
        )
    found = group[name]
    if isinstance(found, h5py.Dataset) and (found.is_virtual or found.external):
        raise ValueError(
            f"{where} is a dataset stored in other files (virtual or external storage); a "
            "Minari file holds its data itself, and a downloaded file never makes this "
            "loader read another"
        )
    return found


_VLEN_REF = 16
"""bytes a variable-length element's reference takes in its dataset (its values lie in
the file's global heap)"""


def read_dataset(dset: Any, here: str, floor: Floor) -> Any:
    """All of ``dset``'s values, once its declared size fits the bytes it stores or what
    is left of the load's ``floor`` (:func:`~imitrl.datasets.minari._bounds.check_declared`);
    a variable-length dataset (encoded images) as a list of arrays, read one element at a
    time, each within what is left of the file's size (heap values are stored as they
    are, but many elements may name one) or of the floor."""
    import h5py

    count = math.prod(dset.shape or ())  # None: an empty (null) dataspace
    stored = dset.id.get_storage_size()  # what the file's own records say it stores
    budget = max(dset.file.id.get_filesize(), 0)
    check_declared(stored, budget, compressed=False, where=f"{here} (its storage)", floor=floor)
    compressed = dset.id.get_create_plist().get_nfilters() > 0
    vlen = h5py.check_vlen_dtype(dset.dtype) is not None
    itemsize = _VLEN_REF if vlen else dset.dtype.itemsize
    check_declared(count * itemsize, stored, compressed=compressed, where=here, floor=floor)
    if not vlen:
        return dset[()]
    if len(dset.shape or ()) != 1:  # an element per step, each counted as it is read
        raise ValueError(f"{here}: variable-length values of shape {dset.shape}, expected [T]")
    values, room = [], budget
    for i in range(len(dset)):
        value = dset[i]
        where = f"{here} (element {i}, after {budget - room:,} bytes of elements before it)"
        check_declared(value.nbytes, room, compressed=False, where=where, floor=floor)
        room = max(room - value.nbytes, 0)
        values.append(value)
    return values


class _Groups:
    """A space's values in HDF5: a group per Dict key / Tuple entry, a dataset per leaf,
    read within the load's ``floor``."""

    def __init__(self, floor: Floor) -> None:
        self.floor = floor

    def child(self, parent: Any, name: str, kind: str, where: str) -> Any:
        import h5py

        if not isinstance(parent, h5py.Group):
            raise ValueError(f"{where.rsplit('/', 1)[0]} should be a group for a {kind} space")
        return node(parent, name, where)

    def leaf(self, node: Any, space: dict, jpeg: bool, where: str) -> Any:
        import h5py

        if not isinstance(node, h5py.Dataset):
            raise ValueError(f"{where} should be a dataset for a {space['type']} space")
        return read_dataset(node, where, self.floor)


def open_hdf5(fd: int, where: str):
    """The Minari HDF5 file behind ``fd`` (a regular file its folder opened), open for
    reading through ``/proc/self/fd`` (the very file checked, whatever its name now
    names); ValueError when it is no readable HDF5 file."""
    import h5py

    try:
        return h5py.File(fd_path(fd), "r")
    except OSError as err:
        raise ValueError(f"{where}: not a readable HDF5 file ({err})") from err


def attrs_metadata(h5file, where: str) -> dict[str, Any]:
    """The metadata Minari < 0.5 kept as root attributes of the HDF5 file."""
    meta = {k: (v.item() if hasattr(v, "item") else v) for k, v in h5file.attrs.items()}
    meta = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in meta.items()}
    if not meta:
        raise ValueError(f"{where}: no metadata.json beside it and no metadata in its attributes")
    return meta


def list_groups(h5, meta: dict[str, Any], where: str) -> EpisodeList:
    """The ``episode_<id>`` groups of the file, in id order (only their names are read)."""

    def found() -> Iterator[tuple[str, int]]:
        for name in h5.keys():
            if not name.startswith("episode_"):
                continue
            suffix = name.removeprefix("episode_")
            if not (suffix.isascii() and suffix.isdigit()):
                raise ValueError(f"{where}: unexpected group name {name!r} (episode_<id>)")
            yield name, int(suffix)

    listing = list_episodes(found(), "episode_{}", meta, where, lambda n: f"{where}: {n}")
    if not len(listing):
        raise ValueError(f"{where}: no episode groups")
    return listing


def _array(group, field: str, here: str, floor: Floor) -> np.ndarray:
    import h5py

    found = node(group, field, f"{here}/{field}")
    if not isinstance(found, h5py.Dataset):
        raise ValueError(f"{here}/{field} should be a dataset")
    values = read_dataset(found, f"{here}/{field}", floor)
    if isinstance(values, list):
        raise ValueError(f"{here}/{field}: variable-length values, expected one number per step")
    return np.asarray(values)


def _infos(group, path: str, here: str) -> list[str]:
    """Paths of the datasets under ``group`` (itself, when it is one: infos stored whole);
    only names are read."""
    import h5py

    if not isinstance(group, h5py.Group):
        return [path]
    return [
        leaf
        for name in group.keys()
        for leaf in _infos(node(group, name, f"{here}/{path}/{name}"), f"{path}/{name}", here)
    ]


def _read_group(
    group,
    name: str,
    ep_id: int,
    spaces: tuple[dict, dict],
    jpeg: bool,
    skipped: dict,
    floor: Floor,
    where: str,
) -> Steps:
    """One ``episode_<id>`` group (per-step infos are listed in ``skipped``), its arrays
    within the load's ``floor``."""
    here = f"{where}: {name}"
    for field in _FIELDS:
        if field not in group:
            raise ValueError(f"{here} has no {field!r}")
    recorded = group.attrs.get("id")
    if recorded is not None and as_count(recorded, "attrs id", here) != ep_id:
        raise ValueError(f"{here}: attrs id={int(recorded)} contradicts the group's name")
    declared = group.attrs.get("total_steps")
    common: dict[str, Any] = {
        "storage": _Groups(floor),
        "jpeg": jpeg,
        "skipped": skipped,
        "where": here,
    }
    obs = decode(
        node(group, "observations", f"{here}/observations"), spaces[0], "observations", **common
    )
    act = decode(node(group, "actions", f"{here}/actions"), spaces[1], "actions", **common)
    if obs is None or act is None:
        raise ValueError(f"{here}: observations and actions must be numeric")
    if "infos" in group:
        for leaf in _infos(node(group, "infos", f"{here}/infos"), "infos", here):
            skipped[leaf] = "per-step infos are not loaded"
    return Steps(
        name=here,
        id=ep_id,
        observations=obs,
        actions=act,
        rewards=_array(group, "rewards", here, floor),
        terminations=_array(group, "terminations", here, floor),
        truncations=_array(group, "truncations", here, floor),
        declared_steps=None if declared is None else as_count(declared, "attrs total_steps", here),
    )


def read_group(
    h5,
    listing: EpisodeList,
    e: int,
    spaces: tuple[dict, dict],
    jpeg: bool,
    skipped: dict[str, str],
    floor: Floor,
    where: str,
) -> Steps:
    """The ``e``-th episode group of the open file (one group read: its datasets only,
    within the load's ``floor``)."""
    name = listing.name(e)
    try:
        group = node(h5, name, f"{where}: {name}")
        ep_id = int(listing.ids[e])
        return _read_group(group, name, ep_id, spaces, jpeg, skipped, floor, where)
    except (OSError, KeyError, RuntimeError) as err:  # h5py's errors for a damaged file
        raise ValueError(f"{where}: unreadable HDF5 data ({type(err).__name__}: {err})") from err
