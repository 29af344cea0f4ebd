"""The Hub's HTTP, bounded in time, size and destination (:class:`HubClient`).

Why urllib and not huggingface_hub's ``HfApi``: the download makes four kinds of
request (a dataset's ``refs``, a ``revision``'s commit, the commit's ``tree`` a page at a
time, each file's ``resolve``), and every one of them must be bounded against a hostile
or broken server. ``HfApi`` (huggingface_hub 2.4, on httpx) asks through one process-wide
client made with ``timeout=None`` and ``follow_redirects=True`` (a stalled answer waits
forever; a redirect goes to any host), reads each answer whole and decodes its
``Content-Encoding`` before imitrl sees a byte (a 4 MB gzip file listing grew the process
to 4.4 GB), and has no deadline over a whole answer. Its client can be replaced
(``set_client_factory``), but only for every user of huggingface_hub in the process at
once, and answers would still be decoded whole. With urllib (proxies from
``HTTP(S)_PROXY``/``NO_PROXY``, as imitrl's file downloads had before) every rule below
is a few lines here; huggingface_hub is still used for the token and the progress bar
(:mod:`~imitrl.datasets.lerobot._hub`).

The rules, with :class:`HubLimits`' defaults:

* **connect** within ``connect_s`` (10 s), then no read may stay silent past ``read_s``
  (30 s, or ``$HF_HUB_DOWNLOAD_TIMEOUT``, huggingface_hub's own name for it);
* **a deadline over each whole answer**, headers and body: ``deadline_s`` (120 s) for an
  API answer; for a file, ``deadline_s`` plus one second per ``min_bytes_per_s`` (32 KiB,
  a 256 kbit/s link) of its listed size, so a 2 GB file gets 17 hours and a trickle is
  cut at the pace of the slowest link the limits allow, and never more than
  ``max_file_s`` (24 h). A timer shuts the request's socket down when its deadline
  passes, so a read blocked on a stall returns at once;
* **a deadline over the whole file list**, every page of it: ``listing_deadline_s``
  (30 min; the Hub lists 1000 entries a page, a few hundred pages for the largest
  datasets), at most ``max_pages`` pages (10,000) and
  :data:`~imitrl.datasets.lerobot._hub_limits.MAX_EMPTY_PAGES` empty pages in a row that
  name a next page (the Hub's never do), so that a list that never ends is refused,
  whatever its pages look like;
* **a file's listed size** is at most ``max_file_bytes`` (50 GiB: the Hub documents 50 GB
  as its maximum per file), so its deadline is bounded too;
* **size**: an API answer may not decode to more than ``max_answer_bytes`` (64 MiB); its
  ``Content-Length`` is checked before a byte is read and a ``gzip`` body (the only
  encoding asked for) is inflated a block at a time, each bounded by the room left
  (``zlib``'s ``max_length``), so a gzip bomb is refused after at most that many bytes
  and never held whole (a 1 GiB bomb: refused in 0.3 s, the process grown by 130 MB, the
  bound and the copies of a growing buffer). A file is asked for with ``Accept-Encoding:
  identity``; an encoded one is refused (its bytes are hashed as they arrive, never
  decoded);
* **redirects** go to ``https`` or the endpoint's own scheme (never ``ftp://``,
  ``file://`` or down from https to http), and to the endpoint's host, or a host listed
  in ``redirect_hosts`` (a domain lists its subdomains). Its default: for the official
  Hub (``https://huggingface.co``), :data:`HUB_CDN_DOMAINS`, the domains the Hub sends
  file downloads to; for any other endpoint (a mirror, a test server), none. At most
  :data:`MAX_REDIRECTS` in a row. The token goes to the endpoint's host only, never to a
  redirect's other host (the CDN's links are signed).

Every refusal and every failure is a ``ValueError`` naming the URL and what was
expected (the command line prints it as one line).
"""

from __future__ import annotations

import http.client
import re
import socket
import threading
import time
import urllib.error
import urllib.request
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import IO
from urllib.parse import SplitResult, urljoin, urlsplit

from imitrl.datasets.lerobot._hub_limits import HubLimits
from imitrl.fs.reading import parse_json

__all__ = ["HUB_CDN_DOMAINS", "MAX_REDIRECTS", "OFFICIAL_HOSTS", "HubClient", "HubLimits"]

OFFICIAL_HOSTS = ("huggingface.co", "hf.co")
"""the official Hub's hosts (``$HF_ENDPOINT`` unset is ``https://huggingface.co``)"""
HUB_CDN_DOMAINS = ("hf.co", "huggingface.co")
"""where the official Hub redirects a file download, with their subdomains: its LFS CDN
(``cdn-lfs.hf.co``, ``cdn-lfs-us-1.hf.co``, ``cdn-lfs.huggingface.co``) and its Xet
storage bridge (``cas-bridge.xethub.hf.co``)"""
MAX_REDIRECTS = 5
"""redirects followed for one request (the Hub uses one: resolve -> CDN)"""
USER_AGENT = "imitrl"


def check_redirect(endpoint: str, source: str, target: str, limits: HubLimits) -> None:
    """ValueError unless ``source`` may redirect to ``target`` (module docstring): the
    scheme is ``https`` or the endpoint's, the host the endpoint's or one of
    ``limits.redirect_hosts`` (default: :data:`HUB_CDN_DOMAINS` for the official Hub)."""
    home, there = urlsplit(endpoint), urlsplit(target)
    schemes = sorted({"https", home.scheme})
    host = (there.hostname or "").lower()
    allowed = limits.redirect_hosts
    if allowed is None:
        allowed = HUB_CDN_DOMAINS if _official(endpoint) else ()
    if there.scheme not in schemes:
        why = f"a scheme other than {' or '.join(schemes)}"
    elif _same_host(home, there):
        return
    elif any(host == d.lower() or host.endswith("." + d.lower()) for d in allowed):
        return
    else:
        why = f"a host other than the endpoint's ({home.hostname})" + (
            f" and {', '.join(allowed)} (with their subdomains)" if allowed else ""
        )
    raise ValueError(
        f"{source}: redirects to {target}, {why}; refused (a host may be allowed with "
        "download_lerobot(limits=HubLimits(redirect_hosts=(...))))"
    )


def _official(endpoint: str) -> bool:
    parts = urlsplit(endpoint)
    return parts.scheme == "https" and (parts.hostname or "").lower() in OFFICIAL_HOSTS


def _port(parts: SplitResult) -> int:
    try:
        port = parts.port
    except ValueError:  # not a port number: matches none
        return -1
    return port or {"http": 80, "https": 443}.get(parts.scheme, 0)


def _same_host(home: SplitResult, there: SplitResult) -> bool:
    """The endpoint's host, on its port (or the default port of https, an upgrade)."""
    if (there.hostname or "").lower() != (home.hostname or "").lower():
        return False
    return _port(there) == _port(home) or (there.scheme == "https" and _port(there) == 443)


class _NoConnection(Exception):
    """A connection not made within ``connect_s`` (not an OSError: urllib would wrap it)."""


class _Deadline:
    """A timer that shuts down every socket of one request when its time is up, so that a
    read blocked on a stall or a trickle returns at once."""

    def __init__(self, seconds: float, rule: str) -> None:
        self.seconds = seconds
        self.rule = rule
        self.at = time.monotonic() + seconds
        self.expired = False
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self._timer = threading.Timer(seconds, self._expire)
        self._timer.daemon = True
        self._timer.start()

    def left(self) -> float:
        return self.at - time.monotonic()

    def watch(self, sock: socket.socket) -> None:
        with self._lock:
            self._sockets.append(sock)
            if not self.expired:
                return
        _shut(sock)

    def _expire(self) -> None:
        with self._lock:
            self.expired = True
            sockets = list(self._sockets)
        for sock in sockets:
            _shut(sock)

    def cancel(self) -> None:
        self._timer.cancel()


def _shut(sock: socket.socket) -> None:
    try:  # the plain socket's shutdown: an SSLSocket's own would drop its TLS state
        socket.socket.shutdown(sock, socket.SHUT_RDWR)
    except OSError:
        pass  # closed already


def _connection(
    base: type, limits: HubLimits, deadline: _Deadline
) -> type[http.client.HTTPConnection]:
    """``base`` (http.client's HTTP or HTTPS connection) connecting within ``connect_s``
    (or what is left of the deadline), then reading with ``read_s``, watched by
    ``deadline``."""

    class Bounded(base):
        def connect(self) -> None:
            self.timeout = max(min(limits.connect_s, deadline.left()), 0.001)
            try:
                super().connect()
            except TimeoutError:
                raise _NoConnection() from None
            self.sock.settimeout(limits.read_s)
            deadline.watch(self.sock)

    return Bounded


class _HTTP(urllib.request.HTTPHandler):
    def __init__(self, connection: type[http.client.HTTPConnection]) -> None:
        super().__init__()
        self._connection = connection

    def http_open(self, req: urllib.request.Request) -> http.client.HTTPResponse:
        return self.do_open(self._connection, req)


class _HTTPS(urllib.request.HTTPSHandler):
    def __init__(self, connection: type[http.client.HTTPConnection]) -> None:
        super().__init__()
        self._connection = connection

    def https_open(self, req: urllib.request.Request) -> http.client.HTTPResponse:
        # typeshed omits HTTPSHandler._context, which its __init__ sets
        context = self._context  # type: ignore[attr-defined]
        return self.do_open(self._connection, req, context=context)


class _Redirects(urllib.request.HTTPRedirectHandler):
    """Follows a redirect only where :func:`check_redirect` allows; the token again to the
    endpoint's own host (urllib drops it on every redirect)."""

    max_redirections = MAX_REDIRECTS

    def __init__(self, client: HubClient) -> None:
        super().__init__()
        self._client = client

    def redirect_request(
        self,
        req: urllib.request.Request,
        fp: IO[bytes],
        code: int,
        msg: str,
        headers: http.client.HTTPMessage,
        newurl: str,
    ) -> urllib.request.Request | None:
        try:
            check_redirect(self._client.endpoint, req.full_url, newurl, self._client.limits)
        except ValueError:
            fp.close()
            raise
        new = super().redirect_request(req, fp, code, msg, headers, newurl)
        home, there = urlsplit(self._client.endpoint), urlsplit(newurl)
        if new is not None and self._client.token and _same_host(home, there):
            new.add_unredirected_header("Authorization", f"Bearer {self._client.token}")
        return new


@dataclass(frozen=True)
class HubClient:
    """Requests to one Hub endpoint under :class:`HubLimits` (module docstring)."""

    endpoint: str
    """``scheme://host[:port]``, no trailing slash"""
    limits: HubLimits
    token: str | None = None
    """sent to the endpoint's host only"""

    def __post_init__(self) -> None:
        parts = urlsplit(self.endpoint)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(
                f"HF_ENDPOINT={self.endpoint!r}: expected http(s)://<host>, the Hub's address"
            )

    def get_json(
        self, url: str, *, within: tuple[float, str] | None = None
    ) -> tuple[object, str | None]:
        """An API answer's JSON (at most ``max_answer_bytes`` decoded) and the next page's
        URL from its ``Link`` header (on the endpoint's host, else refused), or None.

        ``within``: ``(seconds, rule)``, a shorter deadline than ``deadline_s`` for this
        answer (what is left of the file list's) and the rule that sets it, for messages.
        """
        seconds = self.limits.deadline_s
        rule = f"{seconds:g} s for an API answer; set HubLimits(deadline_s=...) to wait longer"
        if within is not None and within[0] < seconds:
            seconds, rule = within
        with self._open(url, seconds, rule, encoding="gzip") as response:
            body = _bounded_body(response, url, self.limits.max_answer_bytes)
            link = _next_link(response.headers.get_all("Link") or [])
        if link is not None:
            link = urljoin(url, link)
            if not _same_host(urlsplit(self.endpoint), urlsplit(link)):
                raise ValueError(f"{url}: its next page is {link}, not on {self.endpoint}")
        return parse_json(body, where=url), link

    @contextmanager
    def stream(self, url: str, size: int) -> Iterator[http.client.HTTPResponse]:
        """The open answer to a file of ``size`` bytes, unencoded, to be read within
        :meth:`HubLimits.file_deadline_s`; errors while it is read are explained too."""
        limits = self.limits
        seconds = limits.file_deadline_s(size)
        rule = (
            f"{limits.deadline_s:g} s + 1 s per {limits.min_bytes_per_s:g} bytes of a "
            f"{size}-byte file"
            + (f", at most {limits.max_file_s:g} s" if seconds == limits.max_file_s else "")
            + "; set HubLimits(deadline_s=..., min_bytes_per_s=..., max_file_s=...) to wait "
            "longer"
        )
        with self._open(url, seconds, rule, encoding="identity") as response:
            coding = (response.headers.get("Content-Encoding") or "identity").strip().lower()
            if coding != "identity":
                raise ValueError(
                    f"{url}: served with Content-Encoding {coding!r}, asked for none; refused"
                )
            yield response

    @contextmanager
    def _open(
        self, url: str, seconds: float, rule: str, *, encoding: str
    ) -> Iterator[http.client.HTTPResponse]:
        deadline = _Deadline(seconds, rule)
        request = urllib.request.Request(
            url, headers={"User-Agent": USER_AGENT, "Accept-Encoding": encoding}
        )
        if self.token:  # never sent on by urllib to a redirect (see _Redirects)
            request.add_unredirected_header("Authorization", f"Bearer {self.token}")
        opener = urllib.request.OpenerDirector()
        for handler in (
            urllib.request.ProxyHandler(),
            urllib.request.UnknownHandler(),
            _HTTP(_connection(http.client.HTTPConnection, self.limits, deadline)),
            _HTTPS(_connection(http.client.HTTPSConnection, self.limits, deadline)),
            urllib.request.HTTPDefaultErrorHandler(),
            _Redirects(self),
            urllib.request.HTTPErrorProcessor(),
        ):
            opener.add_handler(handler)
        try:
            with opener.open(request) as response:
                yield response
            if deadline.expired:  # what was read may have been cut short by it
                raise TimeoutError()
        except Exception as err:
            raise self._explain(err, url, deadline) from None
        finally:
            deadline.cancel()

    def _explain(self, err: Exception, url: str, deadline: _Deadline) -> ValueError:
        """The one-line ValueError an exception met while ``url`` was asked for is."""
        limits = self.limits
        reason = err.reason if isinstance(err, urllib.error.URLError) else err
        if deadline.expired:
            seconds = round(deadline.seconds, 2)
            return ValueError(f"{url}: not received in {seconds:g} s (deadline: {deadline.rule})")
        if isinstance(err, _NoConnection):
            return ValueError(
                f"{url}: no answer in {limits.connect_s:g} s (connect timeout; set "
                "HubLimits(connect_s=...) to wait longer)"
            )
        if isinstance(reason, TimeoutError):
            return ValueError(
                f"{url}: no answer in {limits.read_s:g} s (read timeout; set "
                "HF_HUB_DOWNLOAD_TIMEOUT or HubLimits(read_s=...) to wait longer)"
            )
        if isinstance(err, urllib.error.HTTPError):
            err.close()
            said = err.headers.get("X-Error-Message") or err.headers.get("X-Error-Code") or ""
            return ValueError(
                f"{url}: HTTP {err.code} {err.reason}" + (f" ({said})" if said else "")
            )
        if isinstance(err, ValueError):
            return err
        if isinstance(err, urllib.error.URLError):
            return ValueError(f"{url}: unreachable ({reason})")
        return ValueError(f"{url}: failed ({type(err).__name__}: {err})")


def _bounded_body(response: http.client.HTTPResponse, url: str, limit: int) -> bytes:
    """The body, decoded from gzip if it is, refused past ``limit`` bytes before more is
    held: by its ``Content-Length``, by the bytes read, by the bytes they inflate to."""
    coding = (response.headers.get("Content-Encoding") or "identity").strip().lower()
    if coding not in ("identity", "gzip"):
        raise ValueError(
            f"{url}: answered with Content-Encoding {coding!r}, asked for gzip or none"
        )
    length = (response.headers.get("Content-Length") or "").strip()
    too_big = f"{url}: the answer is larger than {limit} bytes"
    hint = " (HubLimits(max_answer_bytes=...)); refused"
    if length.isdigit() and int(length) > limit:
        raise ValueError(f"{too_big}: Content-Length {length}{hint}")
    inflate = zlib.decompressobj(16 + zlib.MAX_WBITS) if coding == "gzip" else None
    body = bytearray()
    read = 0
    while block := response.read(1 << 16):
        read += len(block)
        if read > limit:
            raise ValueError(f"{too_big}{hint}")
        if inflate is not None:
            try:  # at most one byte past the room left: never more than the bound in memory
                block = inflate.decompress(block, limit - len(body) + 1)
            except zlib.error as err:
                raise ValueError(f"{url}: not gzip as its Content-Encoding says ({err})") from None
        if len(body) + len(block) > limit:
            raise ValueError(f"{too_big} once decoded (Content-Encoding {coding}){hint}")
        body += block
    if length.isdigit() and read != int(length):
        raise ValueError(f"{url}: the answer ends after {read} of its {length} bytes")
    if inflate is not None and not inflate.eof:
        raise ValueError(f"{url}: its gzip answer ends before the gzip stream does")
    return bytes(body)


_LINK = re.compile(r"<([^>]*)>\s*;[^,]*\brel=\"?next\"?")


def _next_link(values: list[str]) -> str | None:
    """The ``rel="next"`` URL of ``Link`` headers (the Hub's pagination, GitHub's form)."""
    for value in values:
        found = _LINK.search(value)
        if found:
            return found.group(1)
    return None
