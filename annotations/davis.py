"""Import DAVIS-style indexed masks: one palette (or 8/16-bit grey) PNG per frame, pixel value
``k`` = object ``k``.

``0`` is background. ``255`` is DAVIS's "void" label (unlabelled boundary band in some releases)
and counts as background by default (``void_value``). Every frame in the folder is annotated for
every mapped object, as in DAVIS: an object whose value does not occur in a frame is *absent* there
(an empty mask), not "not annotated". Several values may map to one query text (their masks are
OR-ed). Values that occur but are not mapped are ignored and listed in ``info["unmapped_values"]``.

Frame names are the PNG stems. ``time_index`` is the stem read as an integer when every stem is one
(DAVIS's ``00000.png`` is frame 0), else the position in sorted order; ``time_index_offset`` is
subtracted in both cases (e.g. 1 when the stems are 1-based).

Every file must be a PNG (checked by its signature: a JPEG named ``.png`` is refused) with a
palette or a single channel (colours are not object ids); its size is read from the header and
refused before decoding when it exceeds :data:`benchmark.core.annotation.MAX_MASK_PIXELS` or differs from
the scene frame of the same name (when a scene is given).
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Iterable, Mapping, Optional

import numpy as np
from PIL import Image

from benchmark.core.errors import InputError
from benchmark.core.imageio import read_png_bytes

from .format import MAX_TIME_INDEX, validate_against_scene
from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query, encode_mask

__all__ = ["import_davis", "read_index_png"]


def read_index_png(path: str | Path, size: Optional[tuple[int, int]] = None) -> np.ndarray:
    """(H, W) integer object indices of a palette / grey PNG (the palette is not applied).

    The file is checked before any pixel is decoded (:func:`benchmark.core.imageio.read_png_bytes`): a PNG
    signature, at most :data:`benchmark.core.annotation.MAX_MASK_PIXELS` pixels, ``size`` =
    ``(height, width)`` when given, and chunks that stay inside the file.
    """
    path = Path(path)
    data, width, height, _, colour = read_png_bytes(path, size)
    if colour not in (0, 3):  # 0 grey, 3 palette; 2 RGB, 4 grey+alpha, 6 RGBA
        kind = {2: "an RGB", 4: "a grey + alpha", 6: "an RGBA"}.get(colour, f"a colour type {colour}")
        raise InputError(path, "mode", f"expected an indexed (palette) or single-channel PNG, got {kind} PNG: "
                                       "colours are not object ids")
    try:
        with Image.open(io.BytesIO(data), formats=["PNG"]) as img:
            img.load()
            mode = img.mode
            ids = np.asarray(img).astype(np.int64) if mode in ("P", "L", "I", "I;16", "1") else None
    # Pillow reports a corrupt stream as any of OSError, SyntaxError, ValueError, EOFError, zlib or
    # struct errors, depending on where it breaks; each means the same thing to the user
    except Exception as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise InputError(path, None, f"cannot decode PNG: {reason}") from None
    if ids is None:
        raise InputError(path, "mode", f"expected an indexed (palette) or single-channel PNG, got mode "
                                       f"{mode!r}: colours are not object ids")
    if ids.shape != (height, width):
        raise InputError(path, None, f"decoded {ids.shape[1]}x{ids.shape[0]} pixels, the header says {width}x{height}")
    return ids


def import_davis(folder: str | Path, labels: Mapping[int, str], *, scene_name: str,
                 sensitive: Optional[Mapping[str, tuple[str, Iterable[Iterable[int]]]]] = None,
                 camera_id: str = "0", num_time_steps: Optional[int] = None, time_index_offset: int = 0,
                 void_value: Optional[int] = 255, pattern: str = "*.png", scene=None) -> AnnotationSet:
    """Build an :class:`AnnotationSet` from a folder of indexed PNGs.

    ``labels``: object value -> query text (values sharing a text are OR-ed).
    ``sensitive``: optional time-sensitive queries ``{text: (base_text, [[l, r], ...])}`` with
    inclusive 0-based ``time_index`` intervals. ``scene``: check the result against this
    :class:`benchmark.core.scene.Scene`.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, None, "folder not found")
    paths = sorted(p for p in folder.glob(pattern) if p.is_file())
    if not paths:
        raise InputError(folder, pattern, "no mask images found")
    if not labels:
        raise InputError(folder, "labels", "give at least one object value -> query text")
    for value, text in labels.items():
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
            raise InputError(folder, f"labels[{value!r}]", "object values are positive integers (0 is background)")
        if void_value is not None and value == void_value:
            raise InputError(folder, f"labels[{value!r}]", f"{value} is the void value")
        if not isinstance(text, str) or not text.strip():
            raise InputError(folder, f"labels[{value!r}]", f"expected a non-empty query text, got {text!r}")

    texts = list(dict.fromkeys(labels.values()))
    queries = [Query(id=i + 1, text=t) for i, t in enumerate(texts)]
    qid = {q.text: q.id for q in queries}
    values_of = {t: np.array([v for v, tt in labels.items() if tt == t], dtype=np.int64) for t in texts}

    stems = [p.stem for p in paths]
    numeric = all(s.isascii() and s.isdigit() for s in stems)
    indices = [int(s) if numeric else i for i, s in enumerate(stems)]
    frames, masks, unmapped = [], {}, set()
    mapped = np.array(sorted(labels), dtype=np.int64)
    scene_sizes = {} if scene is None else {f.name: (f.camera.height, f.camera.width) for f in scene.frames}
    for fid, (path, index) in enumerate(zip(paths, indices), start=1):
        time_index = index - time_index_offset
        if time_index < 0:
            raise InputError(path, "time_index", f"{index} - time_index_offset {time_index_offset} is negative")
        if time_index > MAX_TIME_INDEX:
            raise InputError(path, "time_index", f"{time_index} is past time index {MAX_TIME_INDEX}")
        ids = read_index_png(path, scene_sizes.get(path.stem))
        h, w = ids.shape
        frames.append(AnnotatedFrame(id=fid, name=path.stem, time_index=time_index, width=w, height=h,
                                     camera_id=camera_id))
        present = np.unique(ids)
        unmapped.update(int(v) for v in present if v != 0 and v != void_value and v not in mapped)
        for text in texts:
            masks[(qid[text], fid)] = encode_mask(np.isin(ids, values_of[text]))

    aset = AnnotationSet(scene=scene_name, frames=frames, queries=queries, masks=masks,
                         num_time_steps=num_time_steps,
                         info={"source": "DAVIS-style indexed PNGs", "folder": str(folder),
                               "labels": {str(k): v for k, v in labels.items()},
                               "unmapped_values": sorted(unmapped)})
    for text, spec in (sensitive or {}).items():
        field = f"sensitive[{text!r}]"
        try:
            base_text, intervals = spec
            parsed = [(int(a), int(b)) for a, b in intervals]
        except (TypeError, ValueError):
            raise InputError(folder, field, "expected (base_text, [[l, r], ...])") from None
        if base_text not in qid:
            raise InputError(folder, field, f"base {base_text!r} is not one of the labels' texts")
        if text in qid or any(q.text == text for q in aset.queries):
            raise InputError(folder, field, "repeats an existing query text")
        for a, b in parsed:
            if a < 0 or a > b:
                raise InputError(folder, field, f"bad interval [{a}, {b}] (need 0 <= l <= r)")
        aset.queries.append(Query(id=len(aset.queries) + 1, text=text, kind="sensitive", base=qid[base_text],
                                  intervals=parsed))
    if scene is not None:
        validate_against_scene(aset, scene, file=folder)
    return aset
