"""Bounded decoding: no stored byte decides how much memory a read takes (numpy, numcodecs, zarr's codec
classes and the standard library only).

Two limits:

- A chunk decodes to at most what its array declares a chunk holds (chunk shape x dtype). Every
  decompressing stage of a chunk's codecs goes through :func:`decompress`: a Blosc, LZ4 or zstd frame's
  declared size is read before anything is allocated (and the codec then decodes into exactly that much),
  zlib, gzip, bz2 and lzma streams are decompressed with a cap on their output. A chunk that would decode
  to more is refused (:class:`ChunkTooLarge`): a decompression bomb (megabytes that expand to gigabytes)
  never reaches memory. :func:`bounded_pipeline` builds an array's codec pipeline this way; a codec whose
  output it cannot bound (anything but those compressors, checksums, byte shuffles, transposes and the
  numeric filters delta, fixed-scale-offset, quantize, astype and bitround — e.g. a pickle filter, which
  would run code) is refused by name (:class:`UnboundedCodec`).
- A whole read (a dataset loaded into memory, one array or episode read from disk, one HDF5 dataset
  converted) takes at most the read budget (:func:`read_budget`): ``DSSP_READ_BUDGET`` bytes (a number,
  or with a unit: ``512M``, ``16G``), 4 GiB by default (:data:`DEFAULT_READ_BUDGET`). A read whose declared
  shape x dtype is larger is refused with one line (:func:`check_budget`) before anything is allocated; so
  is an array whose single chunk is larger.
"""

from __future__ import annotations

import bz2
import lzma
import math
import os
import re
import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from dssp_core.errors import ConfigError, DatasetError

READ_BUDGET_ENV = "DSSP_READ_BUDGET"
DEFAULT_READ_BUDGET = 4 << 30
"""Bytes one whole read may take unless ``DSSP_READ_BUDGET`` says otherwise."""

_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}

COMPRESSORS = ("blosc", "zstd", "lz4", "zlib", "gzip", "bz2", "lzma")
"""Decompressing codecs (numcodecs ids) whose output :func:`decompress` bounds."""
SAFE_CODECS = (
    "shuffle",
    "crc32",
    "crc32c",
    "adler32",
    "fletcher32",
    "jenkins_lookup3",
    "delta",
    "fixedscaleoffset",
    "quantize",
    "astype",
    "bitround",
)
"""Codecs (numcodecs ids) whose output is no larger than a bounded input allows: checksums, byte shuffles,
numeric filters (at most 8 bytes per element)."""
_LZMA_MEMORY = 256 << 20
"""Memory an lzma stream's dictionary may take (xz's presets take at most 64 MiB)."""
_FILTER_SLACK = 64
"""Bytes a stage may decode to beyond the chunk's size (checksums appended by later stages)."""


class ChunkTooLarge(ValueError):
    """A compressed chunk declares or decodes to more bytes than a chunk of its array holds."""


class UnboundedCodec(ValueError):
    """An array is stored with a codec whose output this reader cannot bound (its name in the message)."""


# ------------------------------------------------------------------------------------------- the budget
def read_budget() -> int:
    """Bytes one whole read may take: ``DSSP_READ_BUDGET`` (``4G``, ``512M``, ``1.5G`` or a number of
    bytes), :data:`DEFAULT_READ_BUDGET` when unset. An unreadable value is a one-line ConfigError."""
    text = os.environ.get(READ_BUDGET_ENV, "").strip()
    if not text:
        return DEFAULT_READ_BUDGET
    match = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([kmgt]?)i?b?", text.lower())
    value = float(match.group(1)) * _UNITS[match.group(2)] if match else 0.0
    if not match or not math.isfinite(value) or value < 1:
        raise ConfigError(
            f"{READ_BUDGET_ENV}={text!r} is not a size: give bytes, or a number with K, M, G or T "
            f"(e.g. {READ_BUDGET_ENV}=16G)"
        )
    return int(value)


def human_size(nbytes: int) -> str:
    """``5.3 GiB``, ``512.0 MiB``, ``4.0 KiB``, ``12 bytes`` (the units ``DSSP_READ_BUDGET`` takes)."""
    for unit, size in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if nbytes >= size:
            return f"{nbytes / size:.1f} {unit}"
    return f"{int(nbytes)} bytes"


def check_budget(nbytes: int, what: str, remedy: str, error: type[DatasetError] = DatasetError) -> None:
    """Refuse a read of ``nbytes`` (``what`` it reads, e.g. ``"demo.zarr: data/depth steps 0..99"``) over the budget."""
    budget = read_budget()
    if nbytes > budget:
        raise error(
            f"{what} needs {human_size(nbytes)} in memory, over the read budget of {human_size(budget)} "
            f"({READ_BUDGET_ENV}): {remedy}, or raise {READ_BUDGET_ENV} (e.g. {READ_BUDGET_ENV}=16G)"
        )


def nbytes_of(shape, dtype) -> int:
    """Bytes of an array of ``shape`` and ``dtype`` (Python integers: no overflow)."""
    return math.prod(int(n) for n in shape) * np.dtype(dtype).itemsize


# ------------------------------------------------------------------------------------------- frames
_BLOSC_HEADER = 16
_BLOSC_MEMCPYED = 0x02
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


def blosc_problem(read: Callable[[int, int], np.ndarray], size: int, expected_nbytes: int | None) -> str | None:
    """What is wrong with a stored Blosc frame of ``size`` bytes, or None if its header fits the bytes.

    ``read(start, end)`` returns bytes [start, end) of the frame as uint8. c-blosc trusts the header
    (compressed size, block offsets) and reads where it points; checking it against the bytes actually
    stored turns a truncated or overwritten chunk into an error instead of a read past the buffer.
    """
    if size < _BLOSC_HEADER:
        return f"{size} bytes, shorter than a Blosc header"
    head = read(0, _BLOSC_HEADER)
    flags = int(head[2])
    nbytes, blocksize, cbytes = (int(v) for v in np.frombuffer(head[4:16].tobytes(), "<u4"))
    if cbytes > size:
        return f"truncated: {size} of the {cbytes} bytes its Blosc header announces"
    if cbytes != size:
        return f"{size} bytes where its Blosc header announces {cbytes}: not a Blosc frame"
    if expected_nbytes is not None and nbytes != expected_nbytes:
        return f"its Blosc header announces {nbytes} bytes of data, a chunk of this array holds {expected_nbytes}"
    if flags & _BLOSC_MEMCPYED:
        return None if cbytes == nbytes + _BLOSC_HEADER else "its Blosc header is inconsistent (stored uncompressed)"
    if nbytes == 0:
        return None
    if blocksize == 0:
        return "its Blosc header gives a block size of 0"
    first = _BLOSC_HEADER + 4 * -(-nbytes // blocksize)
    if first > size:
        return f"its Blosc block table needs {first} bytes, the file holds {size}"
    starts = np.frombuffer(read(_BLOSC_HEADER, first).tobytes(), "<i4")
    if starts.size and (starts.min() < first or starts.max() >= size):
        return "its Blosc block offsets point outside the file"
    return None


def zstd_content_size(data: bytes | memoryview) -> int | None:
    """The decoded size a zstd frame declares in its header (RFC 8878, 3.1.1.1), None if it declares none.

    A stream that does not start with a zstd frame raises ValueError."""
    if len(data) < 5 or bytes(data[:4]) != _ZSTD_MAGIC:
        raise ValueError("not a zstd frame")
    descriptor = data[4]
    fcs_flag, single_segment, dict_flag = descriptor >> 6, (descriptor >> 5) & 1, descriptor & 3
    start = 5 + (0 if single_segment else 1) + (0, 1, 2, 4)[dict_flag]
    width = (1 if single_segment else 0, 2, 4, 8)[fcs_flag]
    if width == 0:
        return None
    if len(data) < start + width:
        raise ValueError("truncated zstd frame header")
    value = int.from_bytes(bytes(data[start : start + width]), "little")
    return value + 256 if width == 2 else value


def _too_large(declared: int | None, limit: int) -> ChunkTooLarge:
    """``declared``: the size the stream declares, None when decoding it ran past ``limit``."""
    size = f"{human_size(declared)}, more than" if declared is not None else "more than"
    return ChunkTooLarge(
        f"it decodes to {size} the {human_size(limit)} a chunk of this array holds: a "
        f"decompression bomb or a damaged file"
    )


def _stream(make: Callable[[], Any], data: bytes, limit: int, several: bool = True) -> bytes:
    """Decompress the stream in ``data`` (``several``: the concatenated streams) with ``make()`` decompressors,
    at most ``limit`` bytes."""
    out, rest = bytearray(), data
    while True:
        decompressor = make()
        out += decompressor.decompress(rest, limit + 1 - len(out))
        if len(out) > limit:
            raise _too_large(None, limit)
        if not decompressor.eof:
            if getattr(decompressor, "unconsumed_tail", b"") or not getattr(decompressor, "needs_input", True):
                raise _too_large(None, limit)
            raise ValueError("the compressed stream ends early")
        rest = decompressor.unused_data or b""
        if not several or not rest.strip(b"\0"):
            return bytes(out)


def decompress(codec_id: str, data, limit: int, config: dict | None = None):
    """``data`` (bytes-like) decoded by the compressor ``codec_id`` (a numcodecs id), at most ``limit`` bytes.

    ChunkTooLarge when it declares or decodes to more, ValueError when it is not such a stream. ``config``:
    the codec's numcodecs configuration (lzma's ``format`` and ``filters``)."""
    import numcodecs.blosc  # deferred: loads msgpack, numcodecs
    import numcodecs.lz4  # deferred: loads msgpack, numcodecs
    import numcodecs.zstd  # deferred: loads msgpack, numcodecs

    raw = np.frombuffer(memoryview(data).cast("B"), np.uint8)
    if codec_id == "blosc":
        problem = blosc_problem(lambda a, b: raw[a:b], raw.size, None)
        if problem:
            raise ValueError(problem)
        nbytes = int(np.frombuffer(raw[4:8].tobytes(), "<u4")[0])
        if nbytes > limit:
            raise _too_large(nbytes, limit)
        return numcodecs.blosc.decompress(raw)
    if codec_id == "zstd":
        declared = zstd_content_size(raw)
        if declared is None:
            raise ValueError("its zstd frame does not declare its decoded size")
        if declared > limit:
            raise _too_large(declared, limit)
        if declared == 0:
            return b""
        return numcodecs.zstd.decompress(raw, np.empty(declared, np.uint8))  # more frames than declared: an error
    if codec_id == "lz4":
        if raw.size < 4:
            raise ValueError("shorter than an LZ4 header")
        declared = int.from_bytes(raw[:4].tobytes(), "little")
        if declared > limit:
            raise _too_large(declared, limit)
        return numcodecs.lz4.decompress(raw)
    data = raw.tobytes()
    if codec_id == "zlib":
        return _stream(zlib.decompressobj, data, limit, several=False)
    if codec_id == "gzip":
        return _stream(lambda: zlib.decompressobj(16 + zlib.MAX_WBITS), data, limit)
    if codec_id == "bz2":
        return _stream(bz2.BZ2Decompressor, data, limit)
    if codec_id == "lzma":  # the dictionary a stream declares is memory too: at most _LZMA_MEMORY beyond the data
        config = config or {}
        fmt, filters = config.get("format", lzma.FORMAT_AUTO), config.get("filters")
        if fmt == lzma.FORMAT_RAW:
            sizes = [f.get("dict_size", 0) for f in filters or () if isinstance(f, dict)]
            if any(not isinstance(n, int) or n > _LZMA_MEMORY for n in sizes):
                raise ValueError(f"its lzma filters ask for a dictionary of more than {human_size(_LZMA_MEMORY)}")
            return _stream(lambda: lzma.LZMADecompressor(fmt, filters=filters), data, limit)
        return _stream(lambda: lzma.LZMADecompressor(fmt, memlimit=_LZMA_MEMORY + limit), data, limit)
    raise UnboundedCodec(codec_id)


def decompress_frames(kind: str, data, limit: int) -> bytes:
    """A stream of zstd or LZ4 frames (``kind``: ``"zstd"`` or ``"lz4"``, the LZ4 frame format; how ROS 2 bags
    compress their messages and mcap chunks) decoded to at most ``limit`` bytes whatever the frames declare:
    ChunkTooLarge beyond it, ValueError for bytes that are not such a stream. Uses the ``zstd`` module (the
    standard library's from Python 3.14, ``backports.zstd`` before) and ``lz4``, which the bag reader brings."""
    if kind == "zstd":
        try:
            from compression import zstd  # the standard library from Python 3.14
        except ImportError:
            from backports import zstd  # optional: the ros extra (rosbags needs it)
        make, error = zstd.ZstdDecompressor, zstd.ZstdError
    elif kind == "lz4":
        import lz4.frame  # optional: the ros extra (rosbags needs it)

        make, error = lz4.frame.LZ4FrameDecompressor, RuntimeError
    else:
        raise ValueError(f"unknown frame format {kind!r}")
    try:
        return _stream(make, bytes(memoryview(data).cast("B")), limit)
    except error as exc:
        raise ValueError(f"not a {kind} stream ({exc})") from None


# ------------------------------------------------------------------------------------------- codec pipelines
class _BoundedNumcodec:
    """A numcodecs compressor (zarr format 2 ``compressor`` or ``filters`` entry) decoding at most ``limit`` bytes."""

    def __init__(self, codec, limit: int):
        self.codec, self.limit = codec, limit
        self.codec_id = codec.codec_id

    def decode(self, buf, out=None):
        decoded = decompress(self.codec_id, buf, self.limit, self.codec.get_config())
        if out is not None:
            np.copyto(
                np.frombuffer(memoryview(out).cast("B"), np.uint8),
                np.frombuffer(memoryview(decoded).cast("B"), np.uint8),
            )
            return out
        return decoded

    def encode(self, buf):
        return self.codec.encode(buf)

    def get_config(self):
        return self.codec.get_config()


def _codec_id(codec) -> str:
    """The numcodecs id of a zarr 3 codec or a numcodecs codec (``blosc``, ``zstd``, ``bytes``, ``sharding``...)."""
    # deferred: loads msgpack, numcodecs, zarr
    from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, GzipCodec, ShardingCodec, TransposeCodec, ZstdCodec

    native = {
        BloscCodec: "blosc",
        ZstdCodec: "zstd",
        GzipCodec: "gzip",
        Crc32cCodec: "crc32c",
        BytesCodec: "bytes",
        TransposeCodec: "transpose",
        ShardingCodec: "sharding",
    }
    for cls, name in native.items():
        if isinstance(codec, cls):
            return name
    config = getattr(codec, "codec_config", None)
    if isinstance(config, dict) and isinstance(config.get("id"), str):
        return config["id"]
    return str(getattr(codec, "codec_id", None) or type(codec).__name__)


def _numcodec_config(codec) -> dict:
    config = getattr(codec, "codec_config", None)
    return dict(config) if isinstance(config, dict) else {}


def _bytes_codec_class():
    """A zarr BytesBytesCodec that runs its wrapped codec's decoding through :func:`decompress`, bounded by
    the chunk spec it is given (shape x dtype, plus a few bytes for checksums)."""
    from zarr.abc.codec import BytesBytesCodec  # deferred: loads msgpack, numcodecs

    @dataclass(frozen=True)
    class BoundedBytesCodec(BytesBytesCodec):
        inner: Any
        codec_id: str
        config: dict
        is_fixed_size = False

        async def _decode_single(self, chunk_bytes, chunk_spec):
            limit = nbytes_of(chunk_spec.shape, chunk_spec.dtype.to_native_dtype()) + _FILTER_SLACK
            decoded = decompress(self.codec_id, chunk_bytes.as_numpy_array(), limit, self.config)
            return chunk_spec.prototype.buffer.from_array_like(np.frombuffer(memoryview(decoded).cast("B"), np.uint8))

        async def _encode_single(self, chunk_bytes, chunk_spec):
            return await self.inner._encode_single(chunk_bytes, chunk_spec)

        def compute_encoded_size(self, input_byte_length, chunk_spec):
            return self.inner.compute_encoded_size(input_byte_length, chunk_spec)

    return BoundedBytesCodec


_BOUNDED_BYTES = None


def _bounded_codec(codec, chunk_nbytes: int, n_elements: int):
    """``codec`` (one of an array's zarr codecs) with every decompressing stage bounded."""
    global _BOUNDED_BYTES
    from zarr.codecs import ShardingCodec  # deferred: loads msgpack, numcodecs, zarr
    from zarr.codecs._v2 import V2Codec  # deferred: loads msgpack, numcodecs, zarr

    if isinstance(codec, V2Codec):  # zarr format 2: numcodecs compressor and filters
        filters = tuple(codec.filters or ())
        limit = chunk_nbytes if not filters else max(chunk_nbytes, 8 * n_elements) + _FILTER_SLACK

        def bound(numcodec):
            name = str(getattr(numcodec, "codec_id", type(numcodec).__name__))
            if name in COMPRESSORS:
                return _BoundedNumcodec(numcodec, limit)
            if name in SAFE_CODECS:
                return numcodec
            raise UnboundedCodec(name)

        return V2Codec(
            filters=tuple(bound(f) for f in filters) or None,
            compressor=None if codec.compressor is None else bound(codec.compressor),
        )
    name = _codec_id(codec)
    if isinstance(codec, ShardingCodec):
        return replace(
            codec,
            codecs=tuple(_bounded_codec(c, chunk_nbytes, n_elements) for c in codec.codecs),
            index_codecs=tuple(_bounded_codec(c, chunk_nbytes, n_elements) for c in codec.index_codecs),
        )
    if name in COMPRESSORS:
        if _BOUNDED_BYTES is None:
            _BOUNDED_BYTES = _bytes_codec_class()
        return _BOUNDED_BYTES(inner=codec, codec_id=name, config=_numcodec_config(codec))
    if name in SAFE_CODECS or name in ("bytes", "transpose"):
        return codec
    raise UnboundedCodec(name)


def bounded_pipeline(array, chunk_shape: tuple[int, ...], dtype):
    """A codec pipeline that decodes ``array``'s chunks (zarr 2 or 3) like its own, each decompressing stage
    bounded by the chunk's size. UnboundedCodec names a codec whose output cannot be bounded."""
    from zarr.core.codec_pipeline import BatchedCodecPipeline  # deferred: loads msgpack, numcodecs, zarr

    pipeline = array.async_array.codec_pipeline
    codecs = (*pipeline.array_array_codecs, pipeline.array_bytes_codec, *pipeline.bytes_bytes_codecs)
    n_elements = math.prod(int(n) for n in chunk_shape)
    chunk_nbytes = n_elements * np.dtype(dtype).itemsize
    return BatchedCodecPipeline.from_codecs([_bounded_codec(c, chunk_nbytes, n_elements) for c in codecs])
