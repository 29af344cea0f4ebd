"""An episode's Arrow IPC file (Minari's ``arrow`` storage), its sizes checked before it
is decoded.

An IPC file is ``ARROW1\\0\\0``, the stream of messages (a schema, dictionary batches,
record batches: each a flatbuffer header followed by its body), an end-of-stream marker,
a footer and ``ARROW1``. The file is read whole (its own size: no more), then every
message's header is read here - the row count of each record batch, and for a compressed
body the uncompressed size each buffer declares in its first 8 bytes - so that
:func:`~imitrl.datasets.minari._bounds.check_declared` refuses a file declaring more
than its bytes can hold before pyarrow decodes it (decompression allocates what a buffer
declares). The messages are then decoded as a stream, in order, each once: the footer's
block list, which could name one record batch many times, is only checked to be whole
and to count as many record batches as the stream holds.

The headers are flatbuffers (``format/Message.fbs``); the few fields needed are read with
:mod:`struct`, every offset checked to lie inside the header.
"""

from __future__ import annotations

import struct

import pyarrow as pa
import pyarrow.ipc as ipc

__all__ = ["declared_sizes", "read_ipc"]

_MAGIC = b"ARROW1"
_RECORD_BATCH, _DICTIONARY_BATCH = 3, 4  # MessageHeader union tags


class _Flat:
    """A flatbuffer, read field by field with every offset checked."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    def at(self, fmt: str, pos: int) -> int:
        size = struct.calcsize(fmt)
        if pos < 0 or pos + size > len(self.data):
            raise ValueError("an offset outside the message header")
        return struct.unpack_from(fmt, self.data, pos)[0]

    def field(self, table: int, index: int) -> int | None:
        """Where field ``index`` of the table at ``table`` lies, or None when absent."""
        vtable = table - self.at("<i", table)
        slot = 4 + 2 * index
        if slot + 2 > self.at("<H", vtable):
            return None
        offset = self.at("<H", vtable + slot)
        return table + offset if offset else None

    def table(self, table: int, index: int) -> int | None:
        """The table that field ``index`` points to, or None."""
        pos = self.field(table, index)
        return None if pos is None else pos + self.at("<I", pos)

    def scalar(self, table: int, index: int, fmt: str) -> int:
        pos = self.field(table, index)
        return 0 if pos is None else self.at(fmt, pos)


def _batch_sizes(flat: _Flat, batch: int, body: pa.Buffer | None) -> tuple[int, int]:
    """A RecordBatch header's ``(length, bytes its compressed buffers declare)``."""
    length = flat.scalar(batch, 0, "<q")
    if flat.field(batch, 3) is None:  # no BodyCompression: buffers are read in place
        return length, 0
    vector = flat.table(batch, 2)
    if vector is None or body is None:
        return length, 0
    view = memoryview(body)
    unpacked = 0
    for i in range(flat.at("<I", vector)):
        offset = flat.at("<q", vector + 4 + 16 * i)
        size = flat.at("<q", vector + 12 + 16 * i)
        if size < 8 or offset < 0 or offset + 8 > len(view):
            continue  # an empty buffer; one outside the body fails pyarrow's own check
        declared = struct.unpack_from("<q", view, offset)[0]
        unpacked += max(declared, 0)  # -1: stored uncompressed
    return length, unpacked


def declared_sizes(data: pa.Buffer) -> tuple[int, int]:
    """``(rows, bytes)`` an IPC file's messages declare: the record batches' rows, and the
    bytes its compressed buffers take once decompressed (0 when none is compressed).

    Raises:
        ValueError: not an Arrow IPC file (its magic, its footer), a message header that
            cannot be read, a footer counting other record batches than the stream's.
    """
    if data.size < 12 or data.slice(0, 6).to_pybytes() != _MAGIC:
        raise ValueError("not an Arrow IPC file (no ARROW1 magic)")
    footer = ipc.open_file(data).num_record_batches  # the footer only: nothing decoded
    reader = ipc.MessageReader.open_stream(pa.BufferReader(data.slice(8)))
    rows = unpacked = batches = 0
    while True:
        try:
            message = reader.read_next_message()
        except StopIteration:
            if batches != footer:
                raise ValueError(
                    f"its footer lists {footer} record batches, the file holds {batches}"
                ) from None
            return rows, unpacked
        flat = _Flat(message.metadata.to_pybytes())
        root = flat.at("<I", 0)
        kind = flat.scalar(root, 1, "<B")
        header = flat.table(root, 2)
        if header is None or kind not in (_RECORD_BATCH, _DICTIONARY_BATCH):
            continue
        if kind == _DICTIONARY_BATCH:
            batch = flat.table(header, 1)
            if batch is not None:
                unpacked += _batch_sizes(flat, batch, message.body)[1]
            continue
        length, size = _batch_sizes(flat, header, message.body)
        batches += 1
        rows += max(length, 0)
        unpacked += size


def read_ipc(data: pa.Buffer) -> pa.Table:
    """The IPC file's record batches as one table, decoded as a stream from the buffer
    (uncompressed buffers are slices of ``data``, not copies); call once
    :func:`declared_sizes` was checked."""
    return ipc.open_stream(data.slice(8)).read_all()
