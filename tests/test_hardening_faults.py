"""Disk faults and damaged caches: ``eval`` keeps the current results file when the disk fills while it
writes the new one; an ``OSError`` (full, read-only) is one line with exit 2; FIFOs and folders where
files are expected are refused (or recomputed) without hanging; cached arrays are checked for shape and
finiteness when read (warned about and recomputed) and a fit that diverged to NaN is never cached; image
headers past the frame limit and truncated images are one-line errors."""

from __future__ import annotations

import errno
import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from benchmark.cli import main
from benchmark.core.errors import InputError
from benchmark.runner import EvalOptions, evaluate

ROOT = Path(__file__).resolve().parents[1]
RUN = Path("synthetic") / "smoke" / "nearest-frame" / "oracle"


def _options(env, **kw) -> EvalOptions:
    return EvalOptions(method="nearest-frame", scene=str(env["scene"]), results_dir=env["results"],
                       cache_dir=env["cache"], quiet=True, timing_frames=1, timing_repeats=1, **kw)


def _argv(env) -> list[str]:
    return ["eval", "--method", "nearest-frame", "--scene", str(env["scene"]), "--results-dir", str(env["results"]),
            "--cache-dir", str(env["cache"]), "--quiet"]


def one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("warning:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def warnings_of(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("warning:")]


def _fit_folder(env, results: dict) -> Path:
    return env["cache"] / "fits" / "nearest-frame" / "hypernerf-smoke" / results["fit"]["key"]


# -- a full disk while eval replaces its results file -----------------------------------------------------
@pytest.mark.parametrize("where", ["write_results", "write_predictions"])
def test_a_full_disk_while_replacing_keeps_the_current_results_file(env, capsys, monkeypatch, where):
    import benchmark.predictions as predictions
    import benchmark.runner as runner

    first = evaluate(_options(env))
    before = first.path.read_bytes()
    pred_before = sorted(p.name for p in first.path.with_suffix(".predictions").iterdir())

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(runner if where == "write_results" else predictions, where, full)
    capsys.readouterr()
    assert main(_argv(env)) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "No space left on device" in line
    assert first.path.read_bytes() == before  # still the current record, not moved to the archive
    assert sorted(p.name for p in first.path.with_suffix(".predictions").iterdir()) == pred_before
    assert not (env["results"] / "archive").exists() or not list((env["results"] / "archive").rglob("*.json"))
    assert not [p for p in first.path.parent.iterdir() if p.name.startswith(".") and not p.name.endswith(".lock")]


@pytest.mark.parametrize("code,message", [(errno.EROFS, "Read-only file system"), (errno.EACCES, "Permission denied")])
def test_a_read_only_results_or_cache_folder_is_one_line(env, capsys, monkeypatch, code, message):
    import benchmark.core.atomic as atomic

    real = atomic.tempfile.mkstemp

    def refuse(*args, dir=None, **kwargs):  # noqa: A002 - mkstemp's own keyword
        if dir is not None and (str(dir).startswith(str(env["results"])) or str(dir).startswith(str(env["cache"]))):
            raise OSError(code, message, str(dir))
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(atomic.tempfile, "mkstemp", refuse)
    assert main(_argv(env)) == 2
    line = one_error_line(capsys.readouterr().err)
    assert message in line


# -- cached fits: NaN, FIFOs -----------------------------------------------------------------------------
def _poison_npz(path: Path, key_part: str = "features") -> None:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    key = next(k for k, v in arrays.items() if key_part in k and v.dtype.kind == "f" and v.size)
    arrays[key] = np.full_like(arrays[key], np.nan)
    np.savez_compressed(path, **arrays)


def test_a_cached_fit_rewritten_with_nan_is_fitted_again_with_a_warning(env, capsys):
    first = evaluate(_options(env))
    fit = _fit_folder(env, first.results)
    _poison_npz(fit / "model" / "nearest_frame.npz")
    capsys.readouterr()
    again = evaluate(_options(env))
    warnings = warnings_of(capsys.readouterr().err)
    assert len(warnings) == 1 and "fitting again" in warnings[0] and "nearest_frame.npz" in warnings[0], warnings
    assert again.results["timing"]["fit_cached"] is False
    assert again.results["metrics"] == first.results["metrics"]


def test_a_fit_that_diverged_to_nan_is_never_cached(env, capsys, monkeypatch):
    from methods.nearest_frame import NearestFrame

    real = NearestFrame.fit.__func__

    def diverged(cls, *args, **kwargs):
        model = real(cls, *args, **kwargs)
        model.features[0] = tuple(np.full_like(f, np.nan) for f in model.features[0])  # the first view's
        return model

    monkeypatch.setattr(NearestFrame, "fit", classmethod(diverged))
    assert main(_argv(env)) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "non-finite" in line or "NaN" in line
    fits = env["cache"] / "fits" / "nearest-frame" / "hypernerf-smoke"
    assert not [p for p in fits.iterdir() if (p / "fit.json").exists()] if fits.is_dir() else True
    assert not (env["results"] / RUN / "seed0.json").exists()


@pytest.mark.parametrize("entry,said", [("model/nearest_frame.npz", "nearest_frame.npz"),
                                        ("fit.json", "fit.json is a FIFO")])
def test_a_cached_fit_file_that_is_a_fifo_never_hangs_eval_and_is_fitted_again(env, tmp_path, entry, said):
    first = evaluate(_options(env))
    fifo = _fit_folder(env, first.results) / entry
    fifo.unlink()
    os.mkfifo(fifo)
    env_vars = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    try:
        proc = subprocess.run([sys.executable, "-m", "benchmark.cli", *_argv(env)], capture_output=True, text=True,
                              timeout=90, env=env_vars, cwd=str(ROOT))
    except subprocess.TimeoutExpired:
        pytest.fail(f"eval hung on a FIFO at {entry} in the fit cache")
    assert proc.returncode == 0, proc.stderr[-2000:]
    warnings = warnings_of(proc.stderr)
    assert len(warnings) == 1 and said in warnings[0], proc.stderr[-2000:]
    assert fifo.is_file(), "the fit made again replaces the FIFO"


# -- the supervision cache: folders, wrong shapes, NaN ----------------------------------------------------
def _supervision_file(env, prefix: str) -> Path:
    return next((env["cache"] / "supervision").rglob(f"{prefix}-*.npz"))


SUPERVISION_DAMAGE = {
    "segments is a folder": ("segments", lambda p: (p.unlink(), p.mkdir(), (p / "x").write_text("mine"))),
    "features is a folder": ("features", lambda p: (p.unlink(), p.mkdir())),
    "segments of the wrong frame size": ("segments", lambda p: _reshape_levels(p)),
    "features of the wrong width": ("features", lambda p: _reshape_features(p)),
    "features with NaN": ("features", lambda p: _poison_npz(p, "features")),
    "segments is a FIFO": ("segments", lambda p: (p.unlink(), os.mkfifo(p))),
}


def _reshape_levels(path: Path) -> None:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["levels/0"] = np.zeros((3, 5, 5), np.int16)
    np.savez_compressed(path, **arrays)


def _reshape_features(path: Path) -> None:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    key = next(k for k, v in arrays.items() if k.startswith("features/") and v.size)
    arrays[key] = arrays[key][:, :3]
    np.savez_compressed(path, **arrays)


@pytest.mark.parametrize("damage", list(SUPERVISION_DAMAGE))
def test_a_damaged_supervision_cache_entry_is_warned_about_and_recomputed(env, capsys, damage):
    clean = evaluate(_options(env, refit=True))
    prefix, hurt = SUPERVISION_DAMAGE[damage]
    path = _supervision_file(env, prefix)
    hurt(path)
    capsys.readouterr()
    assert main([*_argv(env), "--refit"]) == 0
    err = capsys.readouterr().err
    warnings = warnings_of(err)
    assert warnings and all(path.name in w for w in warnings), err
    assert "Traceback" not in err
    again = json.loads((env["results"] / RUN / "seed0.json").read_text())
    assert again["metrics"] == clean.results["metrics"]


def test_a_resumable_checkpoint_with_nan_is_never_resumed(tmp_path):
    import torch

    from methods.gaussians.checkpoint import Checkpointing, FitCheckpoints

    ck = Checkpointing(tmp_path / "fit.partial.pt", key="k")
    saver = FitCheckpoints(ck, "3dgs", 10)
    saver.save("static", 5, {"means": torch.full((4, 3), float("nan")), "step": 5})
    assert FitCheckpoints(ck, "3dgs", 10).resume is None
    saver.save("static", 5, {"means": torch.zeros(4, 3), "step": 5})
    assert FitCheckpoints(ck, "3dgs", 10).resume is not None
    ck.path.unlink()
    os.mkfifo(ck.path)
    assert FitCheckpoints(ck, "3dgs", 10).resume is None


# -- the annotation lock file ------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_an_annotation_lock_that_is_not_a_file_is_one_line(tmp_path, kind):
    from annotations.tool.session import AnnotationSession
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene
    from benchmark.loaders import load_scene

    scene = load_scene(write_dnerf_scene(rigid_sequence(2, 32, 24, seed=3), tmp_path / "scene"))
    lock = tmp_path / "a.json.lock"
    if kind == "fifo":
        os.mkfifo(lock)
    else:
        lock.mkdir()
    with pytest.raises(InputError, match="lock"):
        AnnotationSession(scene, tmp_path / "a.json").close()
    assert lock.exists()


# -- images -----------------------------------------------------------------------------------------------
def _png_header_only(width: int, height: int) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * 16)) + chunk(b"IEND", b""))


def test_a_huge_png_header_in_a_dnerf_scene_is_one_line(tmp_path, capsys):
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene

    scene = write_dnerf_scene(rigid_sequence(3, 32, 24, seed=2), tmp_path / "scene")
    victim = sorted((scene / "train").glob("*.png"))[1]
    victim.write_bytes(_png_header_only(60000, 60000))
    assert main(["data", "validate", str(scene)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert victim.name in line


def test_data_validate_decodes_every_image(tmp_path, capsys):
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene

    scene = write_dnerf_scene(rigid_sequence(3, 32, 24, seed=2), tmp_path / "scene")
    assert main(["data", "validate", str(scene)]) == 0
    capsys.readouterr()
    victim = sorted((scene / "train").glob("*.png"))[1]
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2])
    assert main(["data", "validate", str(scene)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert victim.name in line


def test_a_truncated_jpeg_is_refused_not_half_decoded(tmp_path):
    import cv2

    from benchmark.core.imageio import read_image

    rng = np.random.default_rng(0)
    img = (rng.random((64, 64, 3)) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    path = tmp_path / "a.jpg"
    path.write_bytes(buf.tobytes())
    assert read_image(path).shape == (64, 64, 3)
    path.write_bytes(buf.tobytes()[: len(buf) // 2])
    with pytest.raises(InputError, match="a.jpg"):
        read_image(path)


def _png(width: int, height: int, *, rows: bytes = b"", stream: bytes = b"") -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", stream or zlib.compress(rows)) + chunk(b"IEND", b""))


_ROWS = b"".join(b"\x00" + bytes(32 * 3) for _ in range(24))  # 32x24 RGB, filter type 0 on every row
_BAD_STREAMS = {
    "too little image data": _png(8000, 8000, rows=b"\x00" * 16),
    "a corrupt stream": _png(32, 24, stream=zlib.compress(_ROWS)[:-4] + b"XXXX"),
    "a stream cut short": _png(32, 24, stream=zlib.compress(_ROWS)[:-6]),
    "too much image data": _png(32, 24, rows=_ROWS + bytes(100)),
    "an unknown row filter": _png(32, 24, rows=b"\x09" + _ROWS[1:]),
    "a chunk failing its CRC": _png(32, 24, rows=_ROWS)[:-25] + b"\x00" + _png(32, 24, rows=_ROWS)[-24:],
}


@pytest.mark.parametrize("fault", sorted(_BAD_STREAMS))
def test_a_png_the_decoder_would_fault_on_is_one_line_and_the_decoder_prints_nothing(fault, tmp_path, capfd):
    """Checked before decoding: libpng would print its own 'libpng error' line to the terminal (C code, past
    Python's stderr) before OpenCV gave up, so stderr must hold our one line only (capfd sees the fd)."""
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene
    from benchmark.core.imageio import read_image, read_mask

    assert read_image(_write(tmp_path / "ok.png", _png(32, 24, rows=_ROWS))).shape == (24, 32, 3)
    scene = write_dnerf_scene(rigid_sequence(3, 32, 24, seed=2), tmp_path / "scene")
    victim = sorted((scene / "train").glob("*.png"))[1]
    victim.write_bytes(_BAD_STREAMS[fault])
    capfd.readouterr()
    assert main(["data", "validate", str(scene)]) == 2
    line = one_error_line(capfd.readouterr().err)
    assert victim.name in line
    for reader in (read_image, read_mask):
        with pytest.raises(InputError, match=victim.name):
            reader(victim)
    assert "libpng" not in capfd.readouterr().err


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _npz_claiming(shape: tuple, held: int) -> bytes:
    """An ``.npz`` whose one member's header declares float64 ``shape`` but holds ``held`` bytes of data."""
    import io
    import zipfile

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": shape})
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as archive:
        archive.writestr("x.npy", header.getvalue() + bytes(held))  # the header writer puts the magic first
    return out.getvalue()


@pytest.mark.parametrize("fault", ["a frame header of 30000x30000", "an npz claiming 16 GiB"])
def test_eval_never_allocates_what_a_generated_scenes_file_claims_and_names_the_file(fault, tmp_path, capfd):
    from benchmark.core.strict import check_npz
    from benchmark.synthetic.generate import generate

    scene = generate("smoke", tmp_path / "smoke", size=32, frames=12)
    if fault.startswith("a frame"):
        victim = sorted((scene / "rgb" / "1x").glob("*.png"))[4]
        victim.write_bytes(_png(30000, 30000, rows=b"\x00" * 16))
    else:
        victim = scene / "truth" / "extra.npz"
        victim.write_bytes(_npz_claiming((2 ** 31,), 64))
        with pytest.raises(InputError, match="declares an array of shape"):
            check_npz(victim)
    capfd.readouterr()
    rc = main(["eval", "--method", "nearest-frame", "--scene", str(scene), "--cache-dir", str(tmp_path / "cache"),
               "--results-dir", str(tmp_path / "results"), "--quiet"])
    assert rc == 2
    line = one_error_line(capfd.readouterr().err)
    assert victim.name in line and "Failed to allocate" not in line and "MemoryError" not in line and "OpenCV" not in line


def test_check_npz_passes_real_arrays_and_refuses_objects_and_non_zips(tmp_path):
    from benchmark.core.strict import check_npz

    np.savez_compressed(tmp_path / "ok.npz", a=np.zeros((40, 50), np.uint16), b=np.ones(3))
    np.savez(tmp_path / "plain.npz", a=np.arange(6.0).reshape(2, 3), empty=np.zeros((0, 4)))
    check_npz(tmp_path / "ok.npz")
    check_npz(tmp_path / "plain.npz")
    np.savez(tmp_path / "objects.npz", a=np.array([{"x": 1}], dtype=object))
    with pytest.raises(InputError, match="Python objects"):
        check_npz(tmp_path / "objects.npz")
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(InputError, match="junk.npz"):
        check_npz(tmp_path / "junk.npz")
    (tmp_path / "big.npz").write_bytes(_npz_claiming((4,), 32))
    check_npz(tmp_path / "big.npz")
    with pytest.raises(InputError, match="more than 16 bytes"):
        check_npz(tmp_path / "big.npz", max_bytes=16)


def test_a_fifo_where_a_scene_file_belongs_is_named_as_a_fifo(tmp_path, capsys):
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene

    scene = write_dnerf_scene(rigid_sequence(3, 32, 24, seed=2), tmp_path / "scene")
    frame = sorted((scene / "train").glob("*.png"))[1]
    frame.unlink()
    os.mkfifo(frame)
    assert main(["data", "validate", str(scene)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert frame.name in line and "FIFO" in line
    other = write_dnerf_scene(rigid_sequence(3, 32, 24, seed=2), tmp_path / "other")
    (other / "transforms_train.json").unlink()
    os.mkfifo(other / "transforms_train.json")
    assert main(["data", "validate", str(other)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "transforms_train.json" in line and "FIFO" in line
