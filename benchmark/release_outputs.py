"""Convert what the 4D LangSplat release's evaluation writes into a bench4d predictions folder.

The release's ``eval/eval.py`` scores its own renders; run with ``--visualize_results`` and
``--detail_results`` it leaves, in its run folder ``<output_path>/<exp_name>/<timestamp>-<tag>/``:

``<NNNNN>/chosen_<query>.png``
    The mask it chose for ``<query>`` on one annotated image (the level with the highest relevance,
    after its smoothing), 0 / 255, one channel. ``NNNNN`` is the COCO **image id** plus one, five digits.
    A time-sensitive query has one on every annotated image (it inherits its base label's images).
``video-query-results-<query>.csv`` (time-sensitive queries)
    Rows ``Type, frame_<i>_iou, ...`` then ``clip similarity``, ``clip meaniou``, ``video similarity``,
    ``video meaniou``: per frame (``i`` = 0-based time index, as the release derives it from the COCO
    file name), the query's similarity to the rendered caption features (``video``) or to the CLIP
    features (``clip``). The release says "present" where the similarity reaches its mean.

:func:`convert_release_outputs` reads those files beside the release's annotation folder (for the image
ids and frame numbers) and writes the masks and, as time-sensitive scores, the chosen similarity row;
bench4d's temporal rule (``release`` protocol: threshold at the mean of the raw scores) then decides.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from pathlib import Path
from typing import Optional

from benchmark.core.errors import InputError, short_repr
from benchmark.core.imageio import read_mask
from benchmark.core.strict import open_regular, terminal_text

from .predictions import QueryPrediction, ScenePredictions, write_predictions

SIMILARITY_ROWS = {"video": "video similarity", "clip": "clip similarity"}
"""Which row of ``video-query-results-<query>.csv`` becomes the time-sensitive scores."""


def image_folder(image_id: int) -> str:
    """The release's per-image folder name: the COCO image id plus one, five digits."""
    return f"{image_id + 1:05d}"


MAX_TABLE_BYTES = 64 << 20
"""Largest ``video-query-results-<query>.csv`` read (the release writes 5 rows of a few hundred numbers: kB)."""
MAX_FIELD_CHARS = 1000
"""Longest field of such a table (a column name or a number is tens of characters)."""
_FRAME_COLUMN = re.compile(r"frame_([0-9]{1,9})_iou", re.ASCII)
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?", re.ASCII)
"""A decimal number as Python or numpy writes one, in ASCII digits: ``float()`` also reads other scripts' digits,
``"1_0"``, ``"inf"`` and ``"nan"``."""


def _table_rows(path: Path) -> list[list[str]]:
    """The rows of the CSV file ``path``: a regular file of at most :data:`MAX_TABLE_BYTES` bytes of UTF-8 whose
    fields hold at most :data:`MAX_FIELD_CHARS` characters; an :class:`InputError` names the file otherwise."""
    with open_regular(path) as handle:  # a FIFO or folder is refused before a read could block
        size = os.fstat(handle.fileno()).st_size
        if size > MAX_TABLE_BYTES:  # checked before reading: the release writes kilobytes
            raise InputError(path, None, f"a table of {size} bytes; at most {MAX_TABLE_BYTES}")
        data = handle.read(MAX_TABLE_BYTES + 1)
    if len(data) > MAX_TABLE_BYTES:  # grown since it was measured
        raise InputError(path, None, f"a table of more than {MAX_TABLE_BYTES} bytes")
    try:
        text = data.decode("utf-8-sig")  # a spreadsheet's byte-order mark is not part of the header
    except UnicodeDecodeError as err:
        line = data.count(b"\n", 0, err.start) + 1
        raise InputError(path, f"line {line}", f"not UTF-8 text (byte {data[err.start]:#04x} at offset "
                                               f"{err.start})") from None
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    rows = []
    try:
        for row in reader:
            long = next((k for k, field in enumerate(row) if len(field) > MAX_FIELD_CHARS), None)
            if long is not None:
                raise InputError(path, f"line {reader.line_num} column {long + 1}", f"a field of {len(row[long])} "
                                 f"characters; at most {MAX_FIELD_CHARS}")
            rows.append(row)
    except csv.Error as err:  # e.g. a field beyond csv's own limit, or a quote never closed
        raise InputError(path, f"line {reader.line_num}", f"not a readable CSV table ({err})") from None
    return rows


def read_similarity_csv(path: Path, row: str) -> dict[int, float]:
    """Time index -> similarity of row ``row`` of a ``video-query-results-<query>.csv``."""
    rows = _table_rows(path)
    if not rows or not rows[0] or rows[0][0] != "Type":
        raise InputError(path, None, "expected the release's header 'Type, frame_<i>_iou, ...'")
    indices: list[int] = []
    seen: set[int] = set()
    for number, column in enumerate(rows[0][1:], start=2):
        match = _FRAME_COLUMN.fullmatch(column)
        if match is None:
            raise InputError(path, f"line 1 column {number}", f"{terminal_text(short_repr(column))} is not a column "
                                                              "named frame_<time index>_iou")
        if int(match.group(1)) in seen:  # the later column would silently replace the earlier one's value
            raise InputError(path, f"line 1 column {number}", f"column {column} appears twice")
        indices.append(int(match.group(1)))
        seen.add(indices[-1])
    found = [(number, r) for number, r in enumerate(rows[1:], start=2) if r and r[0] == row]
    if not found:
        labels = [terminal_text(short_repr(r[0], 40)) for r in rows[1:] if r][:8]
        raise InputError(path, row, f"no row {row!r} (rows: {', '.join(labels)})")
    if len(found) > 1:
        raise InputError(path, row, f"row {row!r} appears twice (rows {found[0][0]} and {found[1][0]} of the table)")
    values = found[0][1][1:]
    if len(values) != len(indices):
        raise InputError(path, row, f"{len(values)} values for {len(indices)} frames")
    out = {}
    for index, value in zip(indices, values):
        number = float(value) if _NUMBER.fullmatch(value.strip()) else math.nan  # 1e400 reads as inf
        if not math.isfinite(number):
            raise InputError(path, f"{row}.frame_{index}", f"not a number: {terminal_text(short_repr(value))} "
                                                           "(expected a finite decimal number)")
        out[index] = number
    return out


def convert_release_outputs(run_folder: str | Path, annotation_folder: str | Path, out_dir: str | Path, *,
                            frame_base: int, scene=None, scene_name: Optional[str] = None,
                            similarity: str = "video", overwrite: bool = False) -> Path:
    """Write the release run ``run_folder``'s masks and time decisions as a bench4d predictions folder.

    ``annotation_folder`` is the release's ``annotations/`` folder the run was scored on; ``frame_base``
    the number of its first frame (1 HyperNeRF, 0 Neu3D); ``scene`` (optional) names the frames as the
    scene does (else the names an :func:`annotations.release.export_release` file records, else
    ``{number:06d}``). ``similarity``: which feature's similarity scores the time-sensitive queries
    (``"video"``, the paper's, or ``"clip"``). Returns the predictions file.
    """
    from annotations.release import import_release_folder

    from benchmark.core.scene import paper_camera

    if similarity not in SIMILARITY_ROWS:
        raise InputError(None, "similarity", f"must be one of {sorted(SIMILARITY_ROWS)}, got {similarity!r}")
    run_folder = Path(run_folder)
    if not run_folder.is_dir():
        raise InputError(run_folder, None, "release run folder not found")
    name = scene_name or (scene.name if scene is not None else Path(annotation_folder).parent.name)
    # the release annotates one camera: where the scene has several, its paper split's
    aset = import_release_folder(annotation_folder, scene_name=name, frame_base=frame_base, frame_names=scene,
                                 camera_id=None if scene is None else paper_camera(scene))
    by_time = {f.time_index: f for f in aset.frames}
    preds = ScenePredictions(scene=name, method="4d-langsplat (release)",
                             info={"converted_from": str(run_folder), "similarity": similarity})
    for query in aset.queries:
        pred = QueryPrediction(text=query.text, kind=query.kind)
        for frame in aset.frames:
            path = run_folder / image_folder(frame.id) / f"chosen_{query.text}.png"
            if path.is_file():
                pred.masks[frame.name] = read_mask(path, (frame.height, frame.width)) > 0
        if not pred.masks:
            raise InputError(run_folder, query.text, f"no chosen_{query.text}.png in any image folder "
                                                     "(run the release's eval.py with --visualize_results)")
        if query.kind == "sensitive":
            table = run_folder / f"video-query-results-{query.text}.csv"
            if not table.is_file():
                raise InputError(table, None, "missing (run the release's eval.py with --detail_results)")
            for index, value in read_similarity_csv(table, SIMILARITY_ROWS[similarity]).items():
                if index in by_time:
                    pred.scores[by_time[index].name] = value
        preds.add(pred)
    return write_predictions(out_dir, preds, overwrite=overwrite)
