"""The file-system boundary: what a downloaded file may name, and how imitrl writes.

* :mod:`~imitrl.fs.contained`: a path a dataset's metadata names must lie inside its
  folder (:func:`inside`, :func:`plain_name`): no ``..``, no absolute path, no link out.
* :mod:`~imitrl.fs.reading`: a folder pinned once, each file opened by descriptor inside
  it, regular files only, a replacement in progress read again (:class:`OpenedFolder`,
  :func:`read_whole`).
* :mod:`~imitrl.fs.files`: files and folders created without following a link, with the
  user's umask (:func:`create_file`, :func:`replace_file`, :class:`PlantedLinkError`).
* :mod:`~imitrl.fs.lock`: one writer per path (:func:`exclusive`), refused at once or
  waited for.
* :mod:`~imitrl.fs.publish`: a folder is written beside its destination and moved into
  place whole, by an atomic exchange (:func:`publishing`).
* :mod:`~imitrl.fs.run_folder`: a job's ``--out``, claimed, staged beside it and
  published whole (:func:`~imitrl.fs.run_folder.claimed`), one rule for every command.
* :mod:`~imitrl.fs.write_errors`: a full disk or a read-only folder names the destination
  (:class:`DiskFullError`, :class:`NotWritableError`).
"""

from imitrl.fs.contained import inside, plain_name, trusted_bases
from imitrl.fs.files import PlantedLinkError, create_file, replace_file
from imitrl.fs.lock import exclusive
from imitrl.fs.publish import publishing
from imitrl.fs.reading import OpenedFolder, ReplacedWhileReading, fd_path, read_whole
from imitrl.fs.write_errors import (
    DiskFullError,
    NotWritableError,
    is_disk_full,
    reporting_disk_full,
)

__all__ = [
    "DiskFullError",
    "NotWritableError",
    "OpenedFolder",
    "PlantedLinkError",
    "ReplacedWhileReading",
    "create_file",
    "exclusive",
    "fd_path",
    "inside",
    "is_disk_full",
    "plain_name",
    "publishing",
    "read_whole",
    "replace_file",
    "reporting_disk_full",
    "trusted_bases",
]
