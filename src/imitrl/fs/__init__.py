"""The file-system boundary: what a downloaded file may name, and how imitrl writes.

* :mod:`~imitrl.fs.contained`: a path a dataset's metadata names must lie inside its
  folder (:func:`inside`, :func:`plain_name`): no ``..``, no absolute path, no link out.
* :mod:`~imitrl.fs.lock`: one writer per path (:func:`exclusive`), refused at once.
* :mod:`~imitrl.fs.publish`: a folder is written beside its destination and moved into
  place whole, by an atomic exchange (:func:`publishing`).
* :mod:`~imitrl.fs.disk_full`: a full disk names the destination (:class:`DiskFullError`).
"""

from imitrl.fs.contained import inside, plain_name, trusted_bases
from imitrl.fs.disk_full import DiskFullError, is_disk_full, reporting_disk_full
from imitrl.fs.lock import exclusive
from imitrl.fs.publish import publishing

__all__ = [
    "DiskFullError",
    "exclusive",
    "inside",
    "is_disk_full",
    "plain_name",
    "publishing",
    "reporting_disk_full",
    "trusted_bases",
]
