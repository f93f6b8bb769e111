"""A CT left on file and read box by box (volume_file): the same voxels, geometry and results as a whole read."""
import gzip
import os
import platform
import zlib

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

from StomachUnfoldLib import io as suio
from StomachUnfoldLib.errors import InputError
from StomachUnfoldLib.frontend import check_volume, return_freed_memory
from StomachUnfoldLib.geometry import Volume
from StomachUnfoldLib.volume_file import FileArray, PackedMask

DIRECTION = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _ct(dtype=np.int16, shape=(37, 29, 23)):
    rng = np.random.default_rng(3)
    a = rng.integers(-1024, 1200, size=shape).astype(dtype)
    return Volume(a, np.array([0.7, 0.8, 2.5]), np.array([-12.0, 30.5, -200.0]), DIRECTION)


def _write(vol, path, compress=True):
    sitk.WriteImage(vol.to_sitk(), str(path), compress)
    return str(path)


def _boxes(shape, n=25, seed=0):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        idx = []
        for s in shape:
            a, b = sorted(rng.integers(0, s + 1, size=2))
            idx.append(slice(int(a), int(max(b, a + 1)), int(rng.integers(1, 4))))
        yield tuple(idx)
    yield (slice(None, None, 4),) * 3
    yield (5, slice(1, 20, 3), 7)
    yield (slice(20, 2, -3), 4, slice(None, None, -2))
    yield (-1, -2, -3)


@pytest.mark.parametrize("name,compress,lazy", [("ct.nrrd", True, True), ("raw.nrrd", False, True),
                                                ("ct.nii.gz", True, True), ("ct.nii", False, True),
                                                ("ct.mha", False, True), ("zip.mha", True, False)])
def test_a_ct_on_file_reads_the_same_voxels_and_geometry_as_a_whole_read(tmp_path, name, compress, lazy):
    path = _write(_ct(), tmp_path / name, compress)
    whole, streamed = suio.read_volume(path), suio.read_volume(path, stream=True)
    assert isinstance(streamed.array, FileArray) is lazy  # compressed MetaImage is decoded whole by ITK: read whole
    for attr in ("spacing", "origin", "direction"):
        np.testing.assert_allclose(getattr(streamed, attr), getattr(whole, attr), atol=1e-6)
    a, s = whole.array, streamed.array
    assert s.shape == a.shape and s.dtype == a.dtype
    if not lazy:
        return
    below = s.below(-500.0)
    assert isinstance(below, PackedMask)
    for idx in _boxes(a.shape):
        np.testing.assert_array_equal(s[idx], a[idx], err_msg=str(idx))
        np.testing.assert_array_equal(below[idx], a[idx] < -500.0, err_msg=str(idx))
    assert s.value_range() == (float(a.min()), float(a.max()), 0)
    np.testing.assert_array_equal(streamed.crop([2, 3, 4], [20, 25, 30]).array, whole.crop([2, 3, 4], [20, 25, 30]).array)
    assert s.materialised == 0
    np.testing.assert_array_equal(np.asarray(s), a)
    assert s.materialised == 1


def test_a_big_endian_raw_nrrd_is_read_in_boxes(tmp_path):
    vol = _ct()
    a = vol.array
    path = tmp_path / "be.nrrd"
    head = ("NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\n"
            f"sizes: {a.shape[2]} {a.shape[1]} {a.shape[0]}\n"
            "space directions: (1,0,0) (0,1,0) (0,0,2)\nkinds: domain domain domain\nendian: big\n"
            "encoding: raw\nspace origin: (0,0,0)\n\n")
    path.write_bytes(head.encode() + a.astype(">i2").tobytes())
    s = suio.read_volume(path, stream=True)
    assert isinstance(s.array, FileArray)
    np.testing.assert_array_equal(np.asarray(s.array), suio.read_volume(path).array)
    np.testing.assert_array_equal(s.array[3:9, ::2, 5], a[3:9, ::2, 5])
    gz = tmp_path / "be_gzip.nrrd"                 # the same data gzip-compressed: decompressed slab by slab
    gz.write_bytes(head.replace("encoding: raw", "encoding: gzip").encode() + gzip.compress(a.astype(">i2").tobytes()))
    g = suio.read_volume(gz, stream=True).array
    assert isinstance(g, FileArray)
    g.scan(-500.0)
    np.testing.assert_array_equal(g[3:9, ::2, 5], a[3:9, ::2, 5])
    np.testing.assert_array_equal(np.asarray(g), a)


def test_slabs_of_a_gzip_nrrd_resume_from_marks_and_match(tmp_path, monkeypatch):
    import StomachUnfoldLib.volume_file as vf

    for name, value in (("MARK_BYTES", 4096), ("GZIP_READ_BYTES", 2048), ("GZIP_CHUNK_BYTES", 3000)):
        monkeypatch.setattr(vf, name, value)  # many resume points, chunks across slices, on a small file
    vol = _ct(shape=(60, 40, 30))
    path = _write(vol, tmp_path / "ct.nrrd")
    s = suio.read_volume(path, stream=True).array
    s.scan(-500.0)
    assert len(s._backend._marks) > 10
    for idx in _boxes(vol.array.shape, seed=5):
        np.testing.assert_array_equal(s[idx], vol.array[idx], err_msg=str(idx))


def test_non_finite_values_are_counted_in_the_scan_and_refused(tmp_path):
    vol = _ct(np.float32)
    vol.spacing = np.array([1.5, 1.5, 2.5])  # large enough to pass the size check
    a = vol.array.copy()
    a[4, 5, 6] = np.nan
    a[30, 1, 2] = np.inf
    path = _write(vol.with_array(a), tmp_path / "f.nrrd")
    s = suio.read_volume(path, stream=True)
    lo, hi, bad = s.array.value_range()
    assert bad == 2 and lo == float(np.nanmin(a[np.isfinite(a)])) and hi == float(a[np.isfinite(a)].max())
    with pytest.raises(InputError, match="2 voxels .* NaN or infinite"):
        check_volume(s)


def test_truncated_nrrd_files_are_refused_with_a_reason(tmp_path):
    path = _write(_ct(shape=(80, 60, 50)), tmp_path / "ct.nrrd")
    data = open(path, "rb").read()
    cut = tmp_path / "cut.nrrd"
    cut.write_bytes(data[:len(data) * 2 // 3])
    s = suio.read_volume(cut, stream=True)
    with pytest.raises(InputError, match="truncated.*export it again") as err:
        s.array.scan(-500.0)
    # the slice named is the one the decompressed data ends in
    body = cut.read_bytes()
    body = body[body.index(b"\n\n") + 2:]
    ends = len(zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(body)) // (60 * 50 * 2) + 1
    assert f"its data ends in slice {ends} of 80;" in str(err.value)
    raw = _write(_ct(shape=(80, 60, 50)), tmp_path / "raw.nrrd", compress=False)
    short = tmp_path / "short.nrrd"
    short.write_bytes(open(raw, "rb").read()[:-1000])
    with pytest.raises(InputError, match="truncated"):
        suio.read_volume(short, stream=True)


def test_the_pipeline_on_a_ct_left_on_file_matches_a_whole_read_and_never_reads_it_whole(tmp_path):
    from StomachUnfoldEval.random_stomach import random_stomach
    from StomachUnfoldLib.pipeline import UnfoldParameters, unfold

    vol, truth = random_stomach(4, size="tiny")[:2]
    path = suio.write_volume(vol, str(tmp_path / "ct.nrrd"))
    params = UnfoldParameters(method="cylindrical")
    whole = unfold(suio.read_volume(path), truth["cardia_lps"], truth["pylorus_lps"], params)
    ct = suio.read_volume(path, stream=True)
    streamed = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], params)
    assert ct.array.materialised == 0
    assert streamed.report["input"] == whole.report["input"]
    assert streamed.report["air_region"] == whole.report["air_region"]
    np.testing.assert_array_equal(streamed.unfolded.array, whole.unfolded.array)
    assert streamed.report.quality["grade"] == whole.report.quality["grade"]


def test_onto_wall_in_slabs_lands_where_the_whole_smoothed_mask_is_one_half():
    from StomachUnfoldLib.quality import onto_wall

    k, j, i = np.mgrid[0:90, 0:40, 0:40]
    lum = (i - 20.0) ** 2 + (j - 20.0) ** 2 < 12.0 ** 2 + 0 * k
    lum[:3] = lum[-3:] = False
    vol = Volume(lum, np.array([0.8, 0.8, 2.5]), np.zeros(3), np.eye(3))
    edge = lum & ~ndimage.binary_erosion(lum, border_value=1)
    pts = vol.voxel_lps(edge)
    moved = onto_wall(pts, vol)
    g = vol.with_array(ndimage.gaussian_filter(lum.astype(np.float32), 1.0))
    changed = np.linalg.norm(moved - pts, axis=1) > 1e-9
    assert changed.mean() > 0.9
    np.testing.assert_allclose(g.sample(moved[changed], order=1, cval=0.0), 0.5, atol=0.02)


_MALLOC_PROBE = """
import resource, sys
import numpy as np
from StomachUnfoldLib.frontend import return_freed_memory
assert return_freed_memory() is True
def rss_mib():
    return int([x for x in open("/proc/self/status") if x.startswith("VmRSS")][0].split()[1]) / 1024
a = np.ones(16 << 17)                        # 16 MiB freed: glibc's own rule would raise its mmap threshold to it
del a
big, small = [], []
for _ in range(8):                           # 8 x 10 MiB, each followed by a small block that stays
    big.append(np.ones(10 << 17))
    small.append(np.ones(1000))
before = rss_mib()
del big
returned = before - rss_mib()
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(200):                         # a flat map's temporaries: 1 MiB arrays made and dropped
    t = np.ones(1 << 17)
    del t
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0
print(returned, faults)
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_freed_memory_is_returned_at_once_on_glibc_and_small_arrays_stay_on_the_heap():
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _MALLOC_PROBE], capture_output=True, text=True, check=True).stdout
    returned_mib, faults = out.split()
    assert float(returned_mib) > 60.0        # crop-sized blocks go back to the system when freed
    assert int(faults) < 5000                # 1 MiB blocks are reused, not mapped anew (200 x 256 pages)


def test_a_file_array_refuses_fancy_indexing(tmp_path):
    s = suio.read_volume(_write(_ct(), tmp_path / "ct.nii"), stream=True).array
    with pytest.raises(IndexError):
        s[np.array([1, 2])]
    with pytest.raises(IndexError):
        s[..., 1]
    assert os.path.basename(s.path) == "ct.nii"


@pytest.mark.parametrize("inflater", ["zlib_ng", "zlib"])
def test_a_gzip_nrrd_reads_the_same_with_zlib_ng_and_with_the_stdlibs_zlib(tmp_path, monkeypatch, inflater):
    # zlib-ng is used where installed (the command line); 3D Slicer bundles only zlib: both give every box and the
    # scan's marks the same, and both refuse damaged data with the one-line reason
    import StomachUnfoldLib.volume_file as vf

    if inflater == "zlib_ng":
        ng = pytest.importorskip("zlib_ng.zlib_ng", reason="zlib-ng is not installed (pip install zlib-ng)")
        monkeypatch.setattr(vf, "_inflate", ng)
    else:
        monkeypatch.setattr(vf, "_inflate", zlib)
    for name, value in (("MARK_BYTES", 4096), ("GZIP_READ_BYTES", 2048), ("GZIP_CHUNK_BYTES", 3000)):
        monkeypatch.setattr(vf, name, value)  # many resume points on a small file
    vol = _ct(shape=(60, 40, 30))
    path = _write(vol, tmp_path / "ct.nrrd")
    s = suio.read_volume(path, stream=True).array
    s.scan(-500.0)
    assert len(s._backend._marks) > 10
    assert all(type(m[2]) is type(vf._inflate.decompressobj()) for m in s._backend._marks)  # its own states
    np.testing.assert_array_equal(s.below(-500.0)[:, :, :], vol.array < -500.0)
    for idx in _boxes(vol.array.shape, seed=7):
        np.testing.assert_array_equal(s[idx], vol.array[idx], err_msg=str(idx))
    data = bytearray(open(path, "rb").read())
    start = data.index(b"\n\n") + 2
    data[start + (len(data) - start) // 2:start + (len(data) - start) // 2 + 64] = b"\xff" * 64
    bad = tmp_path / "bad.nrrd"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match="gzip data is damaged.*export it again"):
        suio.read_volume(bad, stream=True).array.scan(-500.0)
