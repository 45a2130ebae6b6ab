"""Image decoders never speak to the terminal: libpng and libjpeg print their errors and warnings on file
descriptor 2, past Python, and pad what they cannot read. A PNG reaches the decoder with its critical chunks
only, once checked; a JPEG's size is read from its frame header before decoding; whatever a decoder still
says makes the image refused in one line naming the file. Each payload class here printed raw lines (and
some were accepted as padded images) before."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmark.cli import main
from benchmark.core.errors import InputError
from benchmark.core.imageio import read_image, read_mask


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _png(width: int, height: int, depth: int, colour: int, rows: bytes, *, before_idat: bytes = b"",
         after_ihdr: bytes = b"") -> bytes:
    ihdr = _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0))
    return (b"\x89PNG\r\n\x1a\n" + ihdr + after_ihdr + before_idat + _chunk(b"IDAT", zlib.compress(rows))
            + _chunk(b"IEND", b""))


def _rows(width: int, height: int, bytes_per_pixel: float, value: int = 0) -> bytes:
    return b"".join(b"\x00" + bytes([value]) * int(np.ceil(width * bytes_per_pixel)) for _ in range(height))


W, H = 32, 24
PALETTE2 = _chunk(b"PLTE", bytes([0, 0, 0, 255, 0, 0]))
GOOD_PALETTE = _png(W, H, 8, 3, _rows(W, H, 1, 1), before_idat=PALETTE2)
BAD_PNGS = {
    "a palette of 7 bytes": _png(W, H, 8, 3, _rows(W, H, 1), before_idat=_chunk(b"PLTE", bytes(7))),
    "a tRNS longer than the palette": _png(W, H, 8, 3, _rows(W, H, 1),
                                           before_idat=PALETTE2 + _chunk(b"tRNS", bytes(5))),
    "a palette image without a palette": _png(W, H, 8, 3, _rows(W, H, 1)),
    "a second IHDR": _png(W, H, 8, 2, _rows(W, H, 3), after_ihdr=_chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 2,
                                                                                                0, 0, 0))),
    "a palette in a grey image": _png(W, H, 8, 0, _rows(W, H, 1), before_idat=PALETTE2),
}
QUIET_PNGS = {  # damaged ancillary chunks: libpng printed warnings and decoded them; now read as they are
    "a broken colour profile": _png(W, H, 8, 2, _rows(W, H, 3, 7), before_idat=_chunk(b"iCCP", b"x\x00\x00ab")),
    "a zero gamma and a bad sBIT": _png(W, H, 16, 0, _rows(W, H, 2, 9),
                                        before_idat=_chunk(b"gAMA", bytes(4)) + _chunk(b"sBIT", bytes(7))),
}


def _jpeg(size: int = 64, progressive: bool = False) -> bytes:
    img = (np.random.default_rng(0).random((size, size, 3)) * 255).astype(np.uint8)
    params = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else []
    ok, buf = cv2.imencode(".jpg", img, params)
    assert ok
    return buf.tobytes()


def _cut_scan(data: bytes) -> bytes:
    """The JPEG cut a third of the way into its last scan, its end marker put back."""
    scan = data.rfind(b"\xff\xda")
    return data[:scan + (len(data) - scan) // 3] + b"\xff\xd9"


def _huge_jpeg(data: bytes, width: int, height: int) -> bytes:
    sof = data.find(b"\xff\xc0")
    return data[:sof + 5] + struct.pack(">HH", height, width) + data[sof + 9:]


BAD_JPEGS = {
    "a baseline scan cut short": _cut_scan(_jpeg()),
    "a frame header of 20000x20000": _huge_jpeg(_jpeg(), 20000, 20000),
}


@pytest.mark.parametrize("fault", sorted(BAD_PNGS))
def test_a_png_with_a_critical_chunk_out_of_rule_is_one_line_and_nothing_is_printed(fault, tmp_path, capfd):
    path = tmp_path / "x.png"
    path.write_bytes(BAD_PNGS[fault])
    for reader in (read_image, read_mask):
        with pytest.raises(InputError, match="x.png"):
            reader(path)
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("fault", sorted(QUIET_PNGS))
def test_damaged_ancillary_chunks_are_left_out_and_the_pixels_read_quietly(fault, tmp_path, capfd):
    path = tmp_path / "x.png"
    path.write_bytes(QUIET_PNGS[fault])
    img = read_image(path)
    assert img.shape == (H, W, 3) and float(img.max()) > 0
    assert capfd.readouterr().err == ""


def test_a_palette_png_keeps_its_colours_and_transparency(tmp_path):
    path = tmp_path / "p.png"
    path.write_bytes(GOOD_PALETTE)
    assert np.allclose(read_image(path)[..., 0], 1.0) and read_mask(path).max() > 0
    path.write_bytes(_png(W, H, 8, 3, _rows(W, H, 1, 1), before_idat=PALETTE2 + _chunk(b"tRNS", b"\xff\x00")))
    assert read_mask(path).max() == 0, "a fully transparent palette entry is background"


@pytest.mark.parametrize("fault", sorted(BAD_JPEGS))
def test_a_jpeg_the_decoder_would_pad_or_print_about_is_refused_in_one_line(fault, tmp_path, capfd):
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene

    good = tmp_path / "good.jpg"
    good.write_bytes(_jpeg())
    assert read_image(good).shape == (64, 64, 3)
    path = tmp_path / "x.jpg"
    path.write_bytes(BAD_JPEGS[fault])
    with pytest.raises(InputError, match="x.jpg"):
        read_image(path)
    assert capfd.readouterr().err == ""
    # and through a command: a scene's second frame
    scene = write_dnerf_scene(rigid_sequence(3, 32, 24, seed=2), tmp_path / "scene")
    victim = sorted((scene / "train").glob("*.png"))[1]
    victim.write_bytes(BAD_PNGS["a second IHDR"])
    assert main(["data", "validate", str(scene)]) == 2
    err = capfd.readouterr().err
    assert len([line for line in err.splitlines() if line.strip()]) == 1 and victim.name in err, err


def test_the_decoders_capture_leaves_other_output_and_the_descriptor_as_they_were(capfd):
    import os
    import sys

    from benchmark.core.imageio import native_decoder_messages

    before = os.fstat(2)
    with native_decoder_messages() as said:
        os.write(2, b"libpng warning: from C\n")
    assert said == ["libpng warning: from C"]
    after = os.fstat(2)
    assert (before.st_dev, before.st_ino) == (after.st_dev, after.st_ino)
    print("after", file=sys.stderr)
    assert capfd.readouterr().err == "after\n"


def test_every_image_of_the_real_and_generated_scenes_still_reads(tmp_path):
    """No false refusal: the D-NeRF frames beside the repository (when present) and a generated scene's."""
    from benchmark.synthetic.generate import generate

    scene = generate("smoke", tmp_path / "smoke", size=48, frames=8)
    paths = sorted(scene.rglob("*.png"))
    shared = Path(__file__).resolve().parents[2] / "shared" / "data" / "dnerf"
    if shared.is_dir():
        paths += sorted(shared.rglob("*.png"))[::25]
    assert paths
    for path in paths:
        assert read_image(path).ndim == 3


def test_a_write_beyond_the_file_size_limit_names_the_file_and_leaves_the_old_one(tmp_path):
    """Outputs: a write that the disk or a size limit stops is one line naming the file (the child's own
    limit, so that the test's process is untouched); the earlier file is kept whole, no temporary left."""
    import subprocess
    import sys

    target = tmp_path / "out.txt"
    target.write_text("before\n")
    code = ("import resource, sys\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))\n"
            "from benchmark.cli import os_error_line\n"
            "from benchmark.core.atomic import write_text\n"
            "try:\n"
            f"    write_text({str(target)!r}, 'x' * 100000)\n"
            "except OSError as err:\n"
            "    print(os_error_line(err))\n")
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=str(root),
                         env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin", "PYTHONDONTWRITEBYTECODE": "1"})
    assert "out.txt" in out.stdout and "too large" in out.stdout.lower(), out.stdout + out.stderr
    assert target.read_text() == "before\n"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


# -- fourth probe: transparency keys, other formats, file sizes, JPEG scans and trailers -------------------
@pytest.mark.parametrize("colour,trns,ok", [(2, bytes(6), True), (0, bytes(2), True), (6, bytes(8), False),
                                            (4, bytes(2), False), (2, bytes(4), False)])
def test_a_transparency_key_reads_where_its_colour_type_takes_one_and_is_refused_elsewhere(tmp_path, colour, trns, ok,
                                                                                        capfd):
    per_pixel = {0: 1, 2: 3, 4: 2, 6: 4}[colour]
    path = tmp_path / "t.png"
    path.write_bytes(_png(W, H, 8, colour, _rows(W, H, per_pixel, 5), before_idat=_chunk(b"tRNS", trns)))
    if ok:
        assert read_image(path).shape == (H, W, 3) and read_mask(path).shape == (H, W)
    else:
        for reader in (read_image, read_mask):
            with pytest.raises(InputError, match="tRNS"):
                reader(path)
    assert capfd.readouterr().err == ""


def test_a_palette_longer_than_its_bit_depth_indexes_still_reads(tmp_path):
    path = tmp_path / "p.png"
    palette = _chunk(b"PLTE", bytes(range(256)) * 3)
    path.write_bytes(_png(W, H, 4, 3, _rows(W, H, 0.5, 0x11), before_idat=palette))
    assert read_image(path).shape == (H, W, 3)


def test_an_image_in_another_format_is_refused_before_any_decoder_sizes_it(tmp_path):
    ok, bmp = cv2.imencode(".bmp", np.zeros((8, 8, 3), np.uint8))
    path = tmp_path / "000005.png"
    path.write_bytes(bmp.tobytes())
    with pytest.raises(InputError, match="not a PNG or JPEG"):
        read_image(path)


def test_an_image_file_far_larger_than_its_pixels_need_is_refused_before_it_is_read(tmp_path):
    path = tmp_path / "big.png"
    good = _png(W, H, 8, 2, _rows(W, H, 3, 1))
    path.write_bytes(good[:-12] + _chunk(b"tEXt", b"k\x00" + bytes(3_000_000)) + good[-12:])
    with pytest.raises(InputError, match="more than"):
        read_image(path)


def test_a_jpeg_of_thousands_of_scans_is_refused_and_a_trailer_after_its_end_is_not_its_image(tmp_path):
    from benchmark.core.imageio import MAX_JPEG_SCANS, jpeg_layout

    progressive = _jpeg(progressive=True)
    width, height, scans = jpeg_layout("p.jpg", progressive)
    assert (width, height) == (64, 64) and 1 < scans <= MAX_JPEG_SCANS
    # one extra AC scan header repeated: a small file, a long decode
    last = progressive.rfind(b"\xff\xda")
    end = progressive.rfind(b"\xff\xd9")
    many = progressive[:end] + progressive[last:end] * (MAX_JPEG_SCANS + 1) + b"\xff\xd9"
    path = tmp_path / "many.jpg"
    path.write_bytes(many)
    with pytest.raises(InputError, match="scans"):
        read_image(path)
    # a trailer after the end-of-image marker that happens to hold FF DA: the image before it reads
    trailer = tmp_path / "trailer.jpg"
    trailer.write_bytes(_jpeg() + b"ftypmp42" + b"\xff\xda\x00\x08" + bytes(64))
    assert read_image(trailer).shape == (64, 64, 3)


def _npz_member_patched(tmp_path: Path, patch) -> Path:
    """A real compressed npz with its member's bytes changed by ``patch(raw) -> raw``."""
    path = tmp_path / "t.npz"
    np.savez_compressed(path, a=np.arange(4096, dtype=np.float32))
    path.write_bytes(patch(path.read_bytes()))
    return path


@pytest.mark.parametrize("damage", ["encrypted", "bad deflate"])
def test_an_npz_member_that_cannot_be_opened_or_inflated_is_one_error_naming_the_file(tmp_path, damage):
    from benchmark.core.strict import check_npz

    def patch(raw: bytes) -> bytes:
        raw = bytearray(raw)
        if damage == "encrypted":
            raw[6] |= 1
            central = raw.rfind(b"PK\x01\x02")
            raw[central + 8] |= 1
        else:
            start = 30 + int.from_bytes(raw[26:28], "little") + int.from_bytes(raw[28:30], "little")
            raw[start:start + 8] = b"\xff" * 8
        return bytes(raw)

    path = _npz_member_patched(tmp_path, patch)
    with pytest.raises(InputError, match="t.npz"):
        check_npz(path)


def test_a_results_file_in_another_splits_folder_is_refused(tmp_path):
    import shutil

    repo = Path(__file__).resolve().parents[1]
    for folder in ("not-a-split", "novel-view"):
        place = tmp_path / folder / "results" / "dnerf" / "lego" / "langsplat" / "oracle" / folder
        place.mkdir(parents=True)
        shutil.copy(repo / "results" / "dnerf" / "lego" / "langsplat" / "oracle" / "seed0.json", place / "seed0.json")
        assert main(["leaderboard", "--results-dir", str(tmp_path / folder / "results"), "--allow-dirty",
                     "--out", str(tmp_path / folder / "lb.md")]) == 2


def test_recon_never_writes_into_the_scene_it_reads(tmp_path, capsys):
    from benchmark.synthetic.generate import generate

    scene = generate("smoke", tmp_path / "smoke", size=32, frames=8)
    before = sorted(p.relative_to(scene).as_posix() for p in scene.rglob("*"))
    assert main(["recon", "--scene", str(scene), "--model", "3dgs", "--out", str(scene / "renders")]) == 2
    assert "--out" in capsys.readouterr().err
    assert sorted(p.relative_to(scene).as_posix() for p in scene.rglob("*")) == before


def test_a_video_the_decoder_complains_about_is_refused_with_its_message(tmp_path, capfd):
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from test_loaders import write_neu3d

    write_neu3d(tmp_path / "s")
    video = tmp_path / "s" / "cam02.mp4"
    video.write_bytes(video.read_bytes()[:280])  # cut before its index (moov)
    capfd.readouterr()
    assert main(["data", "validate", str(tmp_path / "s")]) == 2
    err = capfd.readouterr().err
    assert len([line for line in err.splitlines() if line.strip()]) == 1 and "cam02.mp4" in err, err


def test_a_png_with_an_unknown_critical_chunk_is_refused_and_an_unknown_ancillary_one_ignored(tmp_path):
    path = tmp_path / "c.png"
    path.write_bytes(_png(W, H, 8, 2, _rows(W, H, 3, 1), before_idat=_chunk(b"ZZZZ", b"x")))
    with pytest.raises(InputError, match="unknown critical"):
        read_image(path)
    path.write_bytes(_png(W, H, 8, 2, _rows(W, H, 3, 1), before_idat=_chunk(b"zzZz", b"x")))
    assert read_image(path).shape == (H, W, 3)


def test_a_truth_file_declaring_more_than_its_frame_can_hold_is_refused_before_loading(tmp_path):
    import io
    import zipfile

    from benchmark.core.truth import load_truth
    from benchmark.synthetic.generate import generate

    scene = generate("smoke", tmp_path / "smoke", size=32, frames=8)
    truth = load_truth(scene)
    name = truth.training_frames[0]
    camera = truth.frames[name].camera
    rows = camera.width * camera.height * 1000  # float32: 4000 bytes a pixel, far more than any truth needs
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": (rows,)})
    with zipfile.ZipFile(scene / "truth" / "levels" / f"{name}.npz", "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("depth.npy", header.getvalue() + bytes(rows * 4))
    with pytest.raises(InputError, match="damaged truth file"):
        truth.levels(name)


def test_bytes_after_the_image_data_stream_and_a_repeated_npz_member_are_refused(tmp_path):
    import zipfile

    from benchmark.core.strict import check_npz

    rows = _rows(W, H, 3, 1)
    ihdr = _chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 2, 0, 0, 0))
    path = tmp_path / "x.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + ihdr + _chunk(b"IDAT", zlib.compress(rows) + b"garbage")
                     + _chunk(b"IEND", b""))
    with pytest.raises(InputError, match="after the end"):
        read_image(path)
    npz = tmp_path / "t.npz"
    np.savez(npz, a=np.zeros(3))
    with zipfile.ZipFile(npz, "a") as archive:
        with pytest.warns(UserWarning):
            archive.writestr("a.npy", _npy_bytes(np.ones(3)))
    with pytest.raises(InputError, match="twice"):
        check_npz(npz)


def _npy_bytes(array: np.ndarray) -> bytes:
    import io

    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def test_a_results_name_with_a_control_character_is_refused(tmp_path):
    import json
    import shutil

    repo = Path(__file__).resolve().parents[1]
    doc = json.loads((repo / "results" / "dnerf" / "lego" / "langsplat" / "oracle" / "seed0.json").read_text())
    doc["method"] = "evil\rname"
    place = tmp_path / "results" / "dnerf" / "lego" / "evil\rname" / "oracle"
    place.mkdir(parents=True)
    (place / "seed0.json").write_text(json.dumps(doc))
    assert main(["leaderboard", "--results-dir", str(tmp_path / "results"), "--allow-dirty",
                 "--out", str(tmp_path / "lb.md"), "--csv-dir", str(tmp_path / "csv")]) == 2
    assert not (tmp_path / "csv").exists()
    shutil.rmtree(tmp_path / "results")
