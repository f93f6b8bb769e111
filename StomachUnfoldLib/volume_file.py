"""A CT read from its file box by box, so that a run's memory grows with the stomach's crop and not with the CT.

``open_volume(path)`` returns a :class:`~StomachUnfoldLib.geometry.Volume` (HU, LPS geometry from SimpleITK)
whose ``array`` is a :class:`FileArray`: it has a NumPy array's ``shape``, ``dtype`` and ``ndim``, and
``array[box]`` reads just that box (k, j, i order) from the file as an ndarray. The front end scans it once in
slabs (the value range and the air below the threshold, packed eight voxels to a byte) and then reads only
the boxes it needs: the retained-fluid rays and the stomach's crop. A 512 x 512 x 500 int16 CT (250 MiB)
then never sits in memory whole.

Formats read in boxes:

* NIfTI (``.nii``, ``.nii.gz``) and uncompressed MetaImage (``.mha``, ``.mhd``): SimpleITK's streaming
  reader (``ImageFileReader`` with an extract region).
* NRRD (``.nrrd``, ``.nhdr`` with the data in the same file, raw or gzip): this module's own reader (ITK's
  NRRD reader decodes the whole file for any region). Raw data is memory-mapped box by box; gzip data is
  decompressed from the start up to the box's last slice (by zlib-ng where it is installed, else by zlib).

Anything else (a DICOM folder, compressed MetaImage, detached NRRD data, other formats) returns None and is
read whole by :func:`StomachUnfoldLib.io.read_volume`.
"""
from __future__ import annotations

import os
import threading
import time
import zlib

import numpy as np

from .errors import InputError

try:  # zlib-ng (pip package zlib-ng): the same inflate, its output byte for byte, about 1.6x faster; else the stdlib's
    from zlib_ng import zlib_ng as _inflate
except ImportError:  # e.g. inside 3D Slicer, which does not bundle it
    _inflate = zlib

__all__ = ["FileArray", "PackedMask", "open_volume", "SLAB_SLICES"]

#: Slices read at a time when a FileArray is scanned whole.
SLAB_SLICES = 16
#: Decompressed bytes between the points a gzip NRRD's later reads resume from (a zlib state each, about 40 kB).
MARK_BYTES = 8 << 20
#: Threads that decompress the parts of one box of a gzip NRRD at once (from the scan's marks).
MAX_READ_THREADS = 4
#: Compressed bytes read, and decompressed bytes produced, at a time from a gzip NRRD.
GZIP_READ_BYTES, GZIP_CHUNK_BYTES = 1 << 20, 4 << 20

_NRRD_TYPES = {
    "signed char": "i1", "int8": "i1", "int8_t": "i1", "uchar": "u1", "unsigned char": "u1", "uint8": "u1",
    "uint8_t": "u1", "short": "i2", "short int": "i2", "signed short": "i2", "signed short int": "i2",
    "int16": "i2", "int16_t": "i2", "ushort": "u2", "unsigned short": "u2", "unsigned short int": "u2",
    "uint16": "u2", "uint16_t": "u2", "int": "i4", "signed int": "i4", "int32": "i4", "int32_t": "i4",
    "uint": "u4", "unsigned int": "u4", "uint32": "u4", "uint32_t": "u4", "float": "f4", "double": "f8",
}


class PackedMask:
    """A bool mask of a whole CT grid stored as bits (eight voxels per byte along i): ``mask[box]`` unpacks a box.

    The air below the threshold of a 512 x 512 x 500 CT takes 16 MiB this way instead of 125 MiB.
    """

    def __init__(self, packed: np.ndarray, shape):
        self.packed, self.shape, self.ndim = packed, tuple(int(s) for s in shape), 3

    def __getitem__(self, index):
        """The mask's voxels at ``index`` (ints, slices, strided slices; k, j, i order) as a bool array or bool."""
        idx = _index(index, self.shape)
        k, j, i = (x if isinstance(x, int) else _slice(x) for x in idx)
        bits = np.unpackbits(self.packed[k, j], axis=-1, count=self.shape[2]).view(bool)
        return bits[..., i]

    def any(self) -> bool:
        """Whether any voxel is set."""
        return bool(self.packed.any())


def _index(index, shape):
    """``index`` (a tuple of up to three ints and slices) as (int or (start, stop, step)) per axis, bounds checked."""
    if not isinstance(index, tuple):
        index = (index,)
    if len(index) > 3 or any(x is Ellipsis for x in index):
        raise IndexError(f"a FileArray takes up to three ints or slices, got {index!r}")
    index = index + (slice(None),) * (3 - len(index))
    out = []
    for x, n in zip(index, shape):
        if isinstance(x, slice):
            out.append(x.indices(n))
        elif isinstance(x, (int, np.integer)):
            v = int(x) + (n if x < 0 else 0)
            if not 0 <= v < n:
                raise IndexError(f"index {int(x)} is out of bounds for an axis of size {n}")
            out.append(v)
        else:
            raise IndexError(f"a FileArray takes ints and slices only, got {type(x).__name__}")
    return out


def _slice(bounds) -> slice:
    """A slice from ``slice.indices``' (start, stop, step); a negative step's stop of -1 means "through 0"."""
    start, stop, step = bounds
    return slice(start, None if stop < 0 else stop, step)


class FileArray:
    """The voxels of a CT file (k, j, i), read box by box: ``a[box]`` is an ndarray read from the file.

    ``scan(threshold_hu)`` reads the file once in slabs of :data:`SLAB_SLICES` slices and keeps the value range,
    the count of non-finite values and the air below ``threshold_hu`` (a :class:`PackedMask`); ``value_range()``
    and ``below(threshold_hu)`` use them. ``np.asarray(a)`` reads the whole file (counted in ``materialised``).
    """

    def __init__(self, backend, shape, dtype, path: str):
        self._backend, self.path = backend, path
        self.shape, self.dtype, self.ndim = tuple(int(s) for s in shape), np.dtype(dtype), 3
        self.size = int(np.prod(self.shape))
        self.nbytes = self.size * self.dtype.itemsize
        self.materialised = 0
        self._range = None
        self._below = {}

    def __repr__(self):
        return f"FileArray({self.path!r}, shape={self.shape}, dtype={self.dtype})"

    def __len__(self):
        return self.shape[0]

    def read_box(self, lo_kji, hi_kji) -> np.ndarray:
        """Voxels ``lo <= (k, j, i) < hi`` as a new (writable) ndarray of this file's dtype."""
        lo = [int(v) for v in lo_kji]
        hi = [int(v) for v in hi_kji]
        if any(h <= l for l, h in zip(lo, hi)):
            return np.zeros([max(h - l, 0) for l, h in zip(lo, hi)], self.dtype)
        return self._backend.read(lo, hi)

    def __getitem__(self, index):
        """The voxels at ``index`` (ints and slices, k, j, i order), read from the file."""
        idx = _index(index, self.shape)
        lo, hi, local = [], [], []
        for x in idx:
            if isinstance(x, int):
                lo.append(x), hi.append(x + 1), local.append(0)
                continue
            start, stop, step = x
            vals = range(start, stop, step)
            if len(vals) == 0:
                lo.append(0), hi.append(0), local.append(slice(0, 0))
                continue
            a, b = min(vals[0], vals[-1]), max(vals[0], vals[-1]) + 1
            lo.append(a), hi.append(b)
            local.append(_slice((start - a, stop - a, step)))  # the same slice, on the box read
        block = self.read_box(lo, hi)
        out = block[tuple(local)]
        return out[()] if out.ndim == 0 else out

    def slabs(self, depth: int = SLAB_SLICES):
        """Yield ``(k0, block)`` for consecutive slabs of ``depth`` slices covering the whole grid (one pass)."""
        if getattr(self._backend, "gzip", False):  # one decompression from the start, not one per slab
            yield from self._backend.gzip_slabs(0, self.shape[0], depth)
            return
        for k0 in range(0, self.shape[0], depth):
            yield k0, self.read_box((k0, 0, 0), (min(k0 + depth, self.shape[0]),) + self.shape[1:])

    def scan(self, threshold_hu: float | None = None, check=None) -> float:
        """Read the file once: value range, non-finite count and (if given) the air below ``threshold_hu`` (HU).

        ``check()``, when given, is called before each slab (it raises to stop the scan). Returns the seconds this
        call spent reading (0 when its results were there already)."""
        need_air = threshold_hu is not None and float(threshold_hu) not in self._below
        if self._range is not None and not need_air:
            return 0.0
        t0 = time.perf_counter()
        lo, hi, bad = np.inf, -np.inf, 0
        packed = np.zeros(self.shape[:2] + ((self.shape[2] + 7) // 8,), np.uint8) if need_air else None
        for k0, block in self.slabs():
            if check is not None:
                check()
            if block.dtype.kind == "f":
                fin = np.isfinite(block)
                n_fin = int(np.count_nonzero(fin))
                bad += block.size - n_fin
                if n_fin:
                    vals = block[fin] if n_fin < block.size else block
                    lo, hi = min(lo, float(vals.min())), max(hi, float(vals.max()))
            else:
                lo, hi = min(lo, float(block.min())), max(hi, float(block.max()))
            if need_air:
                packed[k0:k0 + len(block)] = np.packbits(block < threshold_hu, axis=-1)
        self._range = (lo, hi, bad)
        if need_air:
            self._below[float(threshold_hu)] = PackedMask(packed, self.shape)
        return time.perf_counter() - t0

    def value_range(self) -> tuple[float, float, int]:
        """(lowest, highest finite value, number of NaN or infinite voxels), from one scan of the file."""
        self.scan()
        return self._range

    def below(self, threshold_hu: float) -> PackedMask:
        """The voxels below ``threshold_hu`` (HU) as a PackedMask of the whole grid, from one scan of the file."""
        self.scan(threshold_hu)
        return self._below[float(threshold_hu)]

    def release(self) -> None:
        """Drop the scan's cached masks (the value range is kept)."""
        self._below.clear()

    def __array__(self, dtype=None, copy=None):
        self.materialised += 1
        a = self.read_box((0, 0, 0), self.shape)
        return a if dtype is None else a.astype(dtype, copy=False)

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_below"] = {}
        return state


# ------------------------------------------------------------------------------------------------ backends
class _SitkBackend:
    """Boxes through SimpleITK's streaming reader (an extract region): NIfTI and uncompressed MetaImage."""

    def __init__(self, path: str):
        self.path = path

    def read(self, lo, hi) -> np.ndarray:
        import SimpleITK as sitk

        r = sitk.ImageFileReader()
        r.SetFileName(self.path)
        r.SetExtractIndex([lo[2], lo[1], lo[0]])
        r.SetExtractSize([hi[2] - lo[2], hi[1] - lo[1], hi[0] - lo[0]])
        try:
            return sitk.GetArrayFromImage(r.Execute())
        except RuntimeError as e:
            from .io import itk_reason

            raise InputError(f"cannot read {self.path}: {itk_reason(e)}; the file is damaged, export it again") from None


class _NrrdBackend:
    """Boxes of a NRRD file's attached raw (memory-mapped) or gzip (decompressed up to the box) data."""

    def __init__(self, path: str, offset: int, dtype: np.dtype, shape, gzip: bool):
        self.path, self.offset, self.dtype, self.shape, self.gzip = path, offset, np.dtype(dtype), tuple(shape), gzip
        self.slice_bytes = self.shape[1] * self.shape[2] * self.dtype.itemsize
        self._marks = []  # (uncompressed offset, file offset, zlib state) recorded while decompressing
        self._lock = threading.Lock()

    def __getstate__(self):
        state = {**self.__dict__, "_marks": []}  # zlib states do not pickle; a copy starts from the beginning
        del state["_lock"]
        return state

    def __setstate__(self, state):
        self.__dict__.update(state, _lock=threading.Lock())

    def _native(self, a: np.ndarray) -> np.ndarray:
        return a.astype(self.dtype.newbyteorder("="), copy=True)

    def read(self, lo, hi) -> np.ndarray:
        box = (slice(None), slice(lo[1], hi[1]), slice(lo[2], hi[2]))
        if not self.gzip:
            mm = np.memmap(self.path, self.dtype, "r", self.offset + lo[0] * self.slice_bytes,
                           (hi[0] - lo[0],) + self.shape[1:])
            try:
                return self._native(mm[box])
            finally:
                del mm
        out = np.empty((hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]), self.dtype.newbyteorder("="))

        def part(ka, kb):
            for k0, block in self.gzip_slabs(ka, kb, SLAB_SLICES):
                out[k0 - lo[0]:k0 - lo[0] + len(block)] = block[box]
        parts = self._parts(lo[0], hi[0])
        if len(parts) == 1:
            part(*parts[0])
        else:  # zlib lets go of the GIL while it inflates: parts from their own marks on several cores
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(len(parts)) as pool:
                for fut in [pool.submit(part, a, b) for a, b in parts]:
                    fut.result()
        return out

    def _parts(self, k_lo: int, k_hi: int) -> list[tuple[int, int]]:
        """Slices k_lo..k_hi-1 split into up to one part per core, each starting just after a recorded mark."""
        n = min(os.cpu_count() or 1, MAX_READ_THREADS)
        starts = sorted({-(-m[0] // self.slice_bytes) for m in self._marks})
        starts = [k for k in starts if k_lo < k < k_hi]
        if n < 2 or not starts or k_hi - k_lo < 2 * SLAB_SLICES:
            return [(k_lo, k_hi)]
        cuts = sorted({starts[min(len(starts) - 1, int(round(j * len(starts) / n)))] for j in range(1, n)})
        edges = [k_lo] + cuts + [k_hi]
        return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]

    def _gzip_chunks(self, start: int):
        """Yield ``(u, bytes)``: the data's decompressed bytes from uncompressed offset ``u``, in chunks of at most
        GZIP_CHUNK_BYTES, starting at the last mark at or before byte ``start`` (concatenated gzip members too)."""
        marks = [m for m in self._marks if m[0] <= start]
        with open(self.path, "rb") as f:
            if marks:
                u, c, d = marks[-1][0], marks[-1][1], marks[-1][2].copy()
            else:
                u, c, d = 0, self.offset, _inflate.decompressobj(16 + zlib.MAX_WBITS)
            f.seek(c)
            data = b""
            while True:
                if not data:
                    data = f.read(GZIP_READ_BYTES)
                    if not data:
                        return
                if u >= (self._marks[-1][0] + MARK_BYTES if self._marks else MARK_BYTES):
                    with self._lock:  # parts read in threads: marks stay in order
                        if not self._marks or u >= self._marks[-1][0] + MARK_BYTES:
                            self._marks.append((u, f.tell() - len(data), d.copy()))  # resume here later
                try:
                    out = d.decompress(data, GZIP_CHUNK_BYTES)
                except (zlib.error, _inflate.error) as e:
                    raise InputError(f"cannot read {self.path}: its gzip data is damaged ({e}); export it again") from None
                data = d.unconsumed_tail
                if d.eof:
                    data, d = d.unused_data, _inflate.decompressobj(16 + zlib.MAX_WBITS)
                if out:
                    yield u, out
                    u += len(out)

    def gzip_slabs(self, k_lo: int, k_hi: int, depth: int):
        """Yield (k0, native block) of slices k_lo..k_hi-1, decompressed from the nearest mark before k_lo."""
        sb = self.slice_bytes
        chunks = self._gzip_chunks(k_lo * sb)
        rest, have = memoryview(b""), 0  # the last chunk's bytes not yet used; where the data received ends
        try:
            for k in range(k_lo, k_hi, depth):
                n = min(k + depth, k_hi) - k
                raw = np.empty(n * sb, np.uint8)        # each decompressed byte is copied once, into its slab
                filled = 0
                while filled < len(raw):
                    if not len(rest):
                        u, chunk = next(chunks, (None, None))
                        if chunk is None:
                            raise InputError(f"{self.path} is truncated: its data ends in slice {have // sb + 1} of "
                                             f"{self.shape[0]}; the download or copy was cut, export it again")
                        skip = min(max(k * sb + filled - u, 0), len(chunk))  # bytes before the first slice
                        rest, have = memoryview(chunk)[skip:], u + len(chunk)
                        continue
                    take = min(len(raw) - filled, len(rest))
                    raw[filled:filled + take] = np.frombuffer(rest[:take], np.uint8)
                    rest, filled = rest[take:], filled + take
                block = raw.view(self.dtype).reshape((n,) + self.shape[1:])
                yield k, block if block.dtype.isnative else self._native(block)
        finally:
            chunks.close()


def _nrrd_header(path: str):
    """(fields dict with lower-case keys, data offset in bytes) of a NRRD file, or None if it is not one."""
    with open(path, "rb") as f:
        if not f.read(8).startswith(b"NRRD000"):
            return None
        f.seek(0)
        fields, offset = {}, None
        for _ in range(4096):
            line = f.readline()
            if not line:
                break
            if line in (b"\n", b"\r\n"):
                offset = f.tell()
                break
            text = line.decode("latin-1").rstrip("\r\n")
            if text.startswith("#") or ":" not in text:
                continue
            key, _, value = text.partition(":")
            if value.startswith("="):  # key:=value pairs are metadata
                continue
            fields[key.strip().lower()] = value.strip()
    return (fields, offset) if offset is not None else None


def _nrrd_backend(path: str, shape_kji):
    """A _NrrdBackend for a NRRD file whose attached 3-D scalar data it can read in boxes, else None."""
    head = _nrrd_header(path)
    if head is None:
        return None
    fields, offset = head
    if any(k in fields for k in ("data file", "datafile")) or int(fields.get("line skip", "0") or 0) != 0 \
            or int(fields.get("byte skip", "0") or 0) != 0 or fields.get("dimension") != "3":
        return None
    enc = fields.get("encoding", "").lower()
    code = _NRRD_TYPES.get(fields.get("type", "").lower())
    if enc not in ("raw", "gzip", "gz") or code is None:
        return None
    sizes = [int(v) for v in fields.get("sizes", "").split()]
    if sizes[::-1] != list(shape_kji):
        return None
    dtype = np.dtype(code)
    if dtype.itemsize > 1:
        dtype = dtype.newbyteorder("<" if fields.get("endian", "little").lower() == "little" else ">")
    if enc == "raw" and os.path.getsize(path) < offset + int(np.prod(sizes)) * dtype.itemsize:
        have = os.path.getsize(path) - offset
        raise InputError(f"{path} is truncated: it holds {have} of the {int(np.prod(sizes)) * dtype.itemsize} "
                         "data bytes its header announces; the download or copy was cut, export it again")
    return _NrrdBackend(path, offset, dtype, shape_kji, gzip=enc != "raw")


def _mha_compressed(path: str) -> bool:
    """Whether a MetaImage header says its data is compressed (ITK then decodes the whole file for any region)."""
    with open(path, "rb") as f:
        head = f.read(4096).decode("latin-1", "replace")
    return any(line.replace(" ", "").lower() == "compresseddata=true" for line in head.splitlines())


def open_volume(path):
    """The CT file ``path`` as a Volume (HU, LPS) whose array is a FileArray read in boxes, or None when its
    format is read whole (see the module's docstring); raises InputError for a file that cannot be read."""
    import SimpleITK as sitk

    from .geometry import Volume
    from .io import check_image_information, itk_reason

    path = os.fspath(path)
    low = path.lower()
    if os.path.isdir(path) or not low.endswith((".nrrd", ".nhdr", ".nii", ".nii.gz", ".mha", ".mhd")):
        return None
    r = sitk.ImageFileReader()
    r.SetFileName(path)
    try:
        r.ReadImageInformation()
    except RuntimeError as e:
        raise InputError(f"cannot read {path}: {itk_reason(e)}; check that it is a complete NRRD, NIfTI or MHA "
                         "file (export it again from the viewer)") from None
    check_image_information(r, path)
    shape = tuple(int(s) for s in r.GetSize()[::-1])
    dtype = np.dtype(sitk.GetArrayViewFromImage(sitk.Image([1, 1, 1], r.GetPixelID())).dtype)
    if low.endswith((".nrrd", ".nhdr")):
        backend = _nrrd_backend(path, shape)
        if backend is None or backend.dtype.newbyteorder("=") != dtype.newbyteorder("="):
            return None
    elif low.endswith((".mha", ".mhd")) and _mha_compressed(path):
        return None
    else:
        backend = _SitkBackend(path)
    array = FileArray(backend, shape, dtype.newbyteorder("="), path)
    return Volume(array, np.array(r.GetSpacing()), np.array(r.GetOrigin()), np.array(r.GetDirection()).reshape(3, 3))
