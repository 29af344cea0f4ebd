"""How long and how much a Hub download may take: :class:`HubLimits`, the rules of
:mod:`~imitrl.datasets.lerobot._hub_http` (its module docstring says what each bounds and
why) and of the file list and the cache's lock in :mod:`~imitrl.datasets.lerobot._hub`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

__all__ = ["MAX_EMPTY_PAGES", "HubLimits"]

MAX_EMPTY_PAGES = 10
"""empty pages in a row a file list may send, each naming a next page (the Hub never sends
an empty page with a next one)"""


@dataclass(frozen=True)
class HubLimits:
    """How long and how much a Hub download may take (the rules:
    :mod:`~imitrl.datasets.lerobot._hub_http`'s docstring).

    ``download_lerobot(..., limits=HubLimits(...))`` sets them; without it,
    :meth:`from_env` gives these defaults with ``read_s`` from ``$HF_HUB_DOWNLOAD_TIMEOUT``.
    """

    connect_s: float = 10.0
    """seconds to wait for a connection (TCP and TLS)"""
    read_s: float = 30.0
    """seconds any read may stay silent"""
    deadline_s: float = 120.0
    """seconds a whole API answer may take; a file gets this plus its size's share"""
    min_bytes_per_s: float = 32 * 1024
    """the slowest pace a file may arrive at: its deadline grows by 1 s per this many bytes"""
    max_file_s: float = 24 * 3600.0
    """seconds a file may take at most, whatever its size (24 h: 2 GB at 32 KiB/s fits)"""
    max_file_bytes: int = 50 << 30
    """the largest size a file may be listed with (50 GiB: the Hub documents 50 GB as its
    maximum per file); a larger one is refused before anything is downloaded"""
    max_answer_bytes: int = 64 << 20
    """bytes an API answer may decode to (a tree page, the refs, a revision)"""
    listing_deadline_s: float = 1800.0
    """seconds the whole file list may take, every page of it (each page also within
    ``deadline_s``)"""
    max_pages: int = 10_000
    """pages the file list may come in (the Hub's hold 1000 entries: a million entries in
    1000 pages)"""
    lock_wait_s: float | None = None
    """seconds to wait for another download of the same dataset into the same cache (it
    holds the cache's lock) before giving up naming its process; None: as long as this
    download's own files may take (``deadline_s`` plus each missing file's deadline), the
    longest an unstopped download of them holds the lock (a download of another revision,
    with more to fetch, may hold it longer: set it then)"""
    redirect_hosts: tuple[str, ...] | None = None
    """hosts (a domain: its subdomains too) a redirect may lead to besides the endpoint's;
    None: :data:`~imitrl.datasets.lerobot._hub_http.HUB_CDN_DOMAINS` for the official
    Hub, none for any other endpoint"""

    def __post_init__(self) -> None:
        seconds = ("connect_s", "read_s", "deadline_s", "min_bytes_per_s", "max_file_s")
        for name in (*seconds, "listing_deadline_s", "lock_wait_s"):
            value = getattr(self, name)
            if name == "lock_wait_s" and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"HubLimits.{name} must be a number of seconds, got {value!r}")
            if name == "lock_wait_s" and math.isfinite(value) and value >= 0:
                continue  # 0: refused at once when another download holds the lock
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"HubLimits.{name} must be positive and finite, got {value!r}")
        for name in ("max_answer_bytes", "max_file_bytes", "max_pages"):
            size = getattr(self, name)
            if isinstance(size, bool) or not isinstance(size, int) or size < 1:
                raise ValueError(f"HubLimits.{name} must be a positive int, got {size!r}")
        hosts = self.redirect_hosts
        if hosts is not None and (
            isinstance(hosts, str) or not all(isinstance(h, str) and h for h in hosts)
        ):
            raise ValueError(
                f"HubLimits.redirect_hosts must be a tuple of host names, got {hosts!r}"
            )
        if hosts is not None:  # a list given: kept as a tuple, the dataclass stays hashable
            object.__setattr__(self, "redirect_hosts", tuple(hosts))

    @classmethod
    def from_env(cls) -> HubLimits:
        """The defaults, with ``read_s`` from ``$HF_HUB_DOWNLOAD_TIMEOUT`` when it is set
        (huggingface_hub's timeout of a download's reads); ValueError when it is not a
        positive number."""
        text = os.environ.get("HF_HUB_DOWNLOAD_TIMEOUT", "").strip()
        if not text:
            return cls()
        try:
            return cls(read_s=float(text))
        except ValueError:
            raise ValueError(
                f"HF_HUB_DOWNLOAD_TIMEOUT={text!r}: expected a positive number of seconds"
            ) from None

    def file_deadline_s(self, size: int) -> float:
        """Seconds a file of ``size`` bytes may take: ``deadline_s + size / min_bytes_per_s``,
        at most ``max_file_s``."""
        return min(self.deadline_s + size / self.min_bytes_per_s, self.max_file_s)
