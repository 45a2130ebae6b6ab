"""What a fuzzing probe found in the readers of scene folders, release run folders and release zips: each
hostile input is refused with one :class:`InputError` line naming the file and field, never a traceback from
numpy, csv or zipfile, a numpy warning, or a value taken as if it were sound.

* ``.npy`` files whose header lies about the array's size (``points.npy``, ``poses_bounds.npy``);
* a release run's ``video-query-results-*.csv`` with bytes that are not UTF-8, odd digits, huge fields,
  repeated columns or non-finite values;
* release zips with a damaged, encrypted, unsupported or repeated member;
* HyperNeRF camera, ``metadata.json`` and ``dataset.json`` values beyond any real capture;
* an image header between PIL's warning and error sizes.
"""

from __future__ import annotations

import base64
import io
import json
import shutil
import struct
import warnings
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from benchmark.core.errors import InputError
from benchmark.loaders import load_scene
from tests.test_loaders import write_hypernerf


def npy_bytes(shape: tuple, descr: str = "<f8", data: bytes = b"\0" * 96, version: int = 1) -> bytes:
    """A ``.npy`` file whose header declares ``shape`` of ``descr`` and which then holds ``data``."""
    header = f"{{'descr': {descr!r}, 'fortran_order': False, 'shape': {shape!r}, }}"
    prefix = 10 if version == 1 else 12
    header += " " * (-(prefix + len(header) + 1) % 64) + "\n"
    size = struct.pack("<H", len(header)) if version == 1 else struct.pack("<I", len(header))
    return b"\x93NUMPY" + bytes([version, 0]) + size + header.encode("latin1") + data


def one_line_error(err: pytest.ExceptionInfo, *fragments: str) -> str:
    """The error's text, checked to be one line holding every fragment."""
    message = str(err.value)
    assert "\n" not in message, message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    return message


# -- A: .npy headers ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def hypernerf_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("probe") / "hypernerf"
    write_hypernerf(root, n=6)
    load_scene(root)  # the unmutated scene loads
    return root


@pytest.fixture
def scene_copy(hypernerf_scene, tmp_path):
    root = tmp_path / "scene"
    shutil.copytree(hypernerf_scene, root)
    return root


@pytest.mark.parametrize("rows", [10 ** 9, 10 ** 12])
def test_a_points_npy_whose_header_lies_about_its_size_is_one_line_from_the_cli(scene_copy, capsys, rows):
    from benchmark.cli import main

    (scene_copy / "points.npy").write_bytes(npy_bytes((rows, 3)))
    assert main(["data", "validate", str(scene_copy)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "points.npy" in err and "declares" in err, err


def test_a_poses_bounds_npy_whose_header_lies_about_its_size_is_refused_before_loading(tmp_path):
    root = tmp_path / "neu3d"
    root.mkdir()
    (root / "poses_bounds.npy").write_bytes(npy_bytes((10 ** 12, 17)))
    with pytest.raises(InputError) as err:
        load_scene(root, layout="neu3d")
    one_line_error(err, "poses_bounds.npy", "declares")


def test_check_npy_reads_the_header_only_and_refuses_what_it_cannot_trust(tmp_path):
    from benchmark.core.strict import check_npy

    good = tmp_path / "good.npy"
    np.save(good, np.arange(12, dtype=np.float32).reshape(4, 3))
    assert check_npy(good) == ((4, 3), np.dtype(np.float32))
    cases = {
        "short": (npy_bytes((10 ** 9, 3)), "declares"),
        "long": (npy_bytes((2, 3), data=b"\0" * 200), "declares"),
        "version 2": (npy_bytes((10 ** 9, 3), version=2), "declares"),
        "objects": (npy_bytes((2,), descr="|O", data=b"\0" * 16), "Python objects"),
        "negative": (npy_bytes((-4, -3), data=b"\0" * 96), "shape"),
        "empty elements": (npy_bytes((10 ** 18,), descr="|S0", data=b""), "dtype"),
        "not npy": (b"PK\x03\x04 not an array", "not a readable .npy"),
        "bad header": (b"\x93NUMPY\x01\x00\x10\x00{'descr': <f8   \n", "not a readable .npy"),
        "version 9": (b"\x93NUMPY\x09\x00" + b"\0" * 80, "version"),
        "empty file": (b"", "not a readable .npy"),
    }
    for name, (content, fragment) in cases.items():
        path = tmp_path / f"{name}.npy"
        path.write_bytes(content)
        with pytest.raises(InputError) as err:
            check_npy(path)
        one_line_error(err, str(path), fragment)
    big = tmp_path / "big.npy"
    np.save(big, np.zeros((100, 3)))
    with pytest.raises(InputError, match="at most 1000 bytes"):
        check_npy(big, max_bytes=1000)
    with pytest.raises(InputError, match="dtype"):
        check_npy(good, kinds="iu")
    with pytest.raises(InputError, match="not found"):
        check_npy(tmp_path / "absent.npy")
    with pytest.raises(InputError, match="folder"):
        check_npy(tmp_path)


def test_points_and_poses_of_a_kind_that_is_not_a_number_are_refused_by_their_header(scene_copy, tmp_path):
    np.save(scene_copy / "points.npy", np.zeros((4, 3), dtype=np.complex128))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's ComplexWarning is not an answer
        with pytest.raises(InputError) as err:
            load_scene(scene_copy)
    one_line_error(err, "points.npy", "dtype")
    (tmp_path / "neu3d").mkdir()
    np.save(tmp_path / "neu3d" / "poses_bounds.npy", np.zeros((2, 17), dtype=np.complex64))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError) as err:
            load_scene(tmp_path / "neu3d", layout="neu3d")
    one_line_error(err, "poses_bounds.npy", "dtype")


# -- B: the release's similarity tables ---------------------------------------------------------------------
GOOD_TABLE = ("Type,frame_0_iou,frame_1_iou\nclip similarity,0.5,0.5\nvideo similarity,0.9,0.1\n")


def test_a_well_formed_similarity_table_reads(tmp_path):
    from benchmark.release_outputs import read_similarity_csv

    path = tmp_path / "video-query-results-q.csv"
    path.write_text(GOOD_TABLE, encoding="utf-8")
    assert read_similarity_csv(path, "video similarity") == {0: 0.9, 1: 0.1}


@pytest.mark.parametrize("content, fragment", [
    (GOOD_TABLE.encode().replace(b"0.9", b"0.\xff9"), "UTF-8"),
    ("Type,frame_\u00b2_iou,frame_1_iou\nvideo similarity,0.9,0.1\n".encode(), "frame_"),
    ("Type,frame_\u0663_iou,frame_1_iou\nvideo similarity,0.9,0.1\n".encode(), "frame_"),
    (f"Type,frame_0_iou,frame_1_iou\nvideo similarity,{'9' * 200_000},0.1\n".encode(), "line 2"),
    (b"Type,frame_0_iou,frame_1_iou\nvideo similarity,inf,0.1\n", "video similarity.frame_0"),
    (b"Type,frame_0_iou,frame_1_iou\nvideo similarity,nan,0.1\n", "video similarity.frame_0"),
    (b"Type,frame_0_iou,frame_1_iou\nvideo similarity,1e400,0.1\n", "video similarity.frame_0"),
    ("Type,frame_0_iou,frame_1_iou\nvideo similarity,\u0663,0.1\n".encode(), "video similarity.frame_0"),
    (b"Type,frame_0_iou,frame_0_iou\nvideo similarity,0.9,0.1\n", "twice"),
    (b"Type,frame_0_iou,frame_1_iou\nvideo similarity,0.9,0.1\nvideo similarity,0.1,0.9\n", "twice"),
    (b"Type,frame_99999999999999999999999_iou\nvideo similarity,0.9\n", "frame_"),
    (b'Type,frame_0_iou\nvideo similarity,"0.9\n', "line"),
])
def test_a_damaged_similarity_table_is_one_error_naming_the_file(tmp_path, content, fragment):
    from benchmark.release_outputs import read_similarity_csv

    path = tmp_path / "video-query-results-q.csv"
    path.write_bytes(content)
    with pytest.raises(InputError) as err:
        read_similarity_csv(path, "video similarity")
    one_line_error(err, str(path), fragment)


def test_a_similarity_table_larger_than_any_release_writes_is_refused_before_reading(tmp_path, monkeypatch):
    from benchmark import release_outputs

    monkeypatch.setattr(release_outputs, "MAX_TABLE_BYTES", 100)
    path = tmp_path / "video-query-results-q.csv"
    path.write_text(GOOD_TABLE + "clip meaniou" + ",1.0" * 30 + "\n", encoding="utf-8")
    with pytest.raises(InputError) as err:
        release_outputs.read_similarity_csv(path, "video similarity")
    one_line_error(err, str(path), "at most 100")


def test_a_similarity_table_that_is_a_folder_is_refused(tmp_path):
    from benchmark.release_outputs import read_similarity_csv

    (tmp_path / "video-query-results-q.csv").mkdir()
    with pytest.raises(InputError, match="folder"):
        read_similarity_csv(tmp_path / "video-query-results-q.csv", "video similarity")


# -- C: release zips in the annotation server ---------------------------------------------------------------
@pytest.fixture(scope="module")
def annotation_scene(tmp_path_factory):
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene

    seq = rigid_sequence(4, 64, 48, seed=4, travel_frac=0.2, radius_frac=0.22)
    return load_scene(write_dnerf_scene(seq, tmp_path_factory.mktemp("ann-scene") / "blob"))


@pytest.fixture
def session(annotation_scene, tmp_path):
    from annotations.tool.session import AnnotationSession

    s = AnnotationSession(annotation_scene, tmp_path / "ann" / "blob.json")
    yield s
    s.close()


COCO_MEMBER = "annotations/train/_annotations.coco.json"


def release_zip(*members: tuple[str, bytes], compression: int = zipfile.ZIP_STORED) -> bytes:
    """A zip of ``members`` (a name may repeat: zipfile warns, a hostile upload does not care)."""
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "Duplicate name"
        with zipfile.ZipFile(buf, "w", compression) as zf:
            for name, data in members:
                zf.writestr(name, data)
    return buf.getvalue()


def patched(data: bytes, local: int, central: int, patch) -> bytes:
    """``data`` (a zip of one member) with ``patch(bytearray, offset)`` applied at the local header's field
    offset ``local`` and the central directory's field offset ``central``."""
    out = bytearray(data)
    patch(out, local)
    patch(out, out.rindex(b"PK\x01\x02") + central)
    return bytes(out)


def _bad_crc(buf: bytearray, at: int) -> None:
    """The CRC-32 field changed."""
    buf[at:at + 4] = struct.pack("<I", struct.unpack("<I", buf[at:at + 4])[0] ^ 0xDEADBEEF)


def _method_9(buf: bytearray, at: int) -> None:
    """The compression method set to 9 (deflate64)."""
    buf[at:at + 2] = struct.pack("<H", 9)


def _encrypted(buf: bytearray, at: int) -> None:
    """The encrypted flag set."""
    buf[at] |= 1


COCO = json.dumps({"images": [], "annotations": [], "categories": []}).encode()


def _deflate_garbage() -> bytes:
    """A zip whose one deflated member's stream starts with an invalid block (its headers are sound)."""
    data = bytearray(release_zip((COCO_MEMBER, COCO * 20), compression=zipfile.ZIP_DEFLATED))
    start = 30 + len(COCO_MEMBER)
    data[start:start + 8] = b"\xff" * 8  # an invalid deflate block type
    return bytes(data)


@pytest.mark.parametrize("data, fragment", [
    (patched(release_zip((COCO_MEMBER, COCO)), 14, 16, _bad_crc), "CRC"),
    (patched(release_zip((COCO_MEMBER, COCO)), 8, 10, _method_9), "compression"),
    (patched(release_zip((COCO_MEMBER, COCO)), 6, 8, _encrypted), "encrypted"),
    (_deflate_garbage(), COCO_MEMBER),
    (release_zip((COCO_MEMBER, b"{}"), (COCO_MEMBER, COCO)), "twice"),
    (release_zip(("annotations/video_annotations.json", b"{}"), (COCO_MEMBER, COCO),
                 ("annotations/video_annotations.json", b"{}")), "twice"),
], ids=["bad-crc", "method-9", "encrypted", "bad-deflate", "duplicate-coco", "duplicate-other"])
def test_a_damaged_release_zip_is_a_400_naming_the_member(session, data, fragment):
    with pytest.raises(InputError) as err:
        session.import_data(session.revision, "release", "upload.zip", base64.b64encode(data).decode())
    one_line_error(err, "upload.zip", fragment)
    assert session.revision == 0 and not session.path.exists()


def test_a_duplicated_member_is_named(session):
    data = release_zip((COCO_MEMBER, b"{}"), (COCO_MEMBER, COCO))
    with pytest.raises(InputError) as err:
        session.import_data(session.revision, "release", "upload.zip", base64.b64encode(data).decode())
    one_line_error(err, COCO_MEMBER)


@pytest.mark.parametrize("error", [zipfile.BadZipFile("Bad CRC-32"), zipfile.LargeZipFile("too large"),
                                   zlib.error("invalid block type"), NotImplementedError("method 9"),
                                   RuntimeError("encrypted"), EOFError("stream ended")])
def test_any_zip_or_zlib_error_of_an_import_is_an_input_error(session, monkeypatch, error):
    from annotations.tool import exchange

    def trip(*args, **kwargs):
        raise error

    monkeypatch.setattr(exchange, "import_set", trip)
    with pytest.raises(InputError) as err:
        session.import_data(session.revision, "release", "upload.zip",
                            base64.b64encode(release_zip((COCO_MEMBER, COCO))).decode())
    one_line_error(err, "upload.zip", type(error).__name__)
    assert session.revision == 0


# -- D: HyperNeRF camera, metadata and dataset values -------------------------------------------------------
def edit_json(path: Path, change) -> None:
    """Apply ``change(doc)`` to the JSON file ``path``."""
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def setter(**values):
    """A change setting top-level keys."""
    return lambda doc: doc.update(values)


def load_quietly(root: Path, **options):
    """``load_scene`` with any warning an error: a numpy overflow warning is not an answer."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return load_scene(root, **options)


@pytest.mark.parametrize("change, field", [
    (setter(focal_length=5e-324), "focal_length"),  # a denormal: 0 where denormals are flushed
    (setter(focal_length=1e-300), "focal_length"),
    (setter(focal_length=1e308, pixel_aspect_ratio=10), "focal_length"),
    (setter(focal_length=1e8), "focal_length"),
    (setter(pixel_aspect_ratio=1e308), "pixel_aspect_ratio"),
    (setter(pixel_aspect_ratio=1e-300), "pixel_aspect_ratio"),
    (setter(principal_point=[1e308, -1e308]), "principal_point"),
    (setter(principal_point=[10.0, -2e7]), "principal_point"),
    (setter(radial_distortion=[1e308, 0.0, 0.0]), "radial_distortion"),
    (setter(radial_distortion=1e308), "radial_distortion"),
    (setter(tangential_distortion=[0.0, -1e308]), "tangential_distortion"),
    (setter(skew=1e308), "skew"),
    (setter(image_size=[1e15, 1e15]), "image_size"),
    (setter(image_size=[65536, 48]), "image_size"),
    (setter(image_size=[64.5, 48]), "image_size"),
    (setter(image_size=[True, 48]), "image_size"),
])
def test_a_camera_value_beyond_any_real_camera_is_refused_naming_the_camera_file(scene_copy, change, field):
    camera = scene_copy / "camera" / "000001.json"  # a training frame: its frustum makes the scene's bounds
    edit_json(camera, change)
    with pytest.raises(InputError) as err:
        load_quietly(scene_copy)
    one_line_error(err, str(camera), field)


def test_camera_values_at_the_bounds_still_load(scene_copy):
    camera = scene_copy / "camera" / "000001.json"
    edit_json(camera, setter(focal_length=1e7, pixel_aspect_ratio=2.0, principal_point=[1e7, -1e7]))
    scene = load_quietly(scene_copy)
    assert scene.frames[0].camera.fx > 0


@pytest.mark.parametrize("key, value", [
    ("warp_id", 1e300), ("warp_id", 3.0), ("warp_id", 2 ** 53 + 1), ("warp_id", {}),
    ("camera_id", {}), ("camera_id", -1), ("camera_id", 1e300), ("camera_id", "left"),
    ("appearance_id", 1e300), ("appearance_id", [1]), ("appearance_id", -3),
    ("time_id", 1e300),
])
def test_a_metadata_id_that_is_not_a_sane_integer_is_refused(scene_copy, key, value):
    meta = scene_copy / "metadata.json"
    edit_json(meta, lambda doc: doc["000002"].__setitem__(key, value))
    with pytest.raises(InputError) as err:
        load_quietly(scene_copy)
    one_line_error(err, str(meta), f"000002.{key}")


def test_metadata_without_the_optional_ids_still_loads(scene_copy):
    def drop(doc):
        for entry in doc.values():
            entry.pop("camera_id")
            entry.pop("appearance_id")
            entry.pop("time_id")
    edit_json(scene_copy / "metadata.json", drop)
    assert len(load_quietly(scene_copy).frames) == 6


@pytest.mark.parametrize("change, field", [
    (lambda d: d["train_ids"].append(d["train_ids"][0]), "train_ids"),
    (lambda d: (d["train_ids"].remove(d["ids"][1]), d.__setitem__("val_ids", [d["ids"][1]] * 2)), "val_ids"),
    (lambda d: d.__setitem__("val_ids", [d["train_ids"][0]]), "val_ids"),
    (setter(count=-1), "count"),
    (setter(count=1e300), "count"),
    (setter(count="6"), "count"),
    (setter(num_exemplars=2.5), "num_exemplars"),
    (setter(num_exemplars=None), "num_exemplars"),
])
@pytest.mark.parametrize("rule", ["every4", "auto"])
def test_a_dataset_json_with_repeated_ids_or_bad_counts_is_refused(scene_copy, change, field, rule):
    dataset = scene_copy / "dataset.json"
    edit_json(dataset, change)
    with pytest.raises(InputError) as err:
        load_quietly(scene_copy, split_rule=rule)
    one_line_error(err, str(dataset), field)


def test_a_dataset_json_without_the_optional_keys_still_loads(scene_copy):
    def drop(doc):
        for key in ("count", "num_exemplars", "train_ids", "val_ids"):
            doc.pop(key)
    edit_json(scene_copy / "dataset.json", drop)
    assert len(load_quietly(scene_copy).frames) == 6


@pytest.mark.shared
def test_the_real_hypernerf_camera_and_dataset_files_pass_the_checks():
    from benchmark.core.atomic import read_json
    from benchmark.loaders.hypernerf import _read_dataset_ids, read_camera

    real = Path(__file__).resolve().parents[1].parent / "shared" / "formats" / "hypernerf-chickchicken"
    if not real.is_dir():
        pytest.skip("no ../shared/formats/hypernerf-chickchicken")
    camera = read_camera(real / "camera" / "000001.json")
    assert camera.width == 1072 and camera.height == 1920
    ids, train, val = _read_dataset_ids(real / "dataset.json")
    assert len(ids) == read_json(real / "dataset.json")["count"] and not val


# -- E: image headers between PIL's warning and error sizes -------------------------------------------------
def png_chunk(kind: bytes, body: bytes) -> bytes:
    """One PNG chunk: length, type, body and CRC."""
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png_header(width: int, height: int) -> bytes:
    """A PNG declaring ``width`` x ``height`` RGB pixels and holding none (an empty IDAT)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", b"") + png_chunk(b"IEND", b"")


@pytest.mark.parametrize("side", [10_000, 13_000])  # 100 M and 169 M pixels: PIL warns, it does not refuse
def test_an_image_header_of_a_hundred_million_pixels_is_one_error_and_no_warning(tmp_path, side):
    from benchmark.loaders import _common

    path = tmp_path / "big.png"
    path.write_bytes(png_header(side, side))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(InputError) as err:
            _common.image_size(path)
    one_line_error(err, str(path), "pixels")
    assert not caught, [str(w.message) for w in caught]


# -- fourth probe: path-equivalent member names ------------------------------------------------------------
@pytest.mark.parametrize("alias", ["annotations/train/./_annotations.coco.json", "annotations//train/_annotations.coco.json"])
def test_one_member_under_two_spellings_of_its_path_is_refused(session, alias):
    data = release_zip((COCO_MEMBER, COCO), (alias, b"{}"))
    with pytest.raises(InputError) as err:
        session.import_data(session.revision, "release", "upload.zip", base64.b64encode(data).decode())
    one_line_error(err, "appears twice")
