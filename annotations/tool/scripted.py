"""Scripted annotation sessions: ``bench4d annotate`` driven in headless Chromium by a plan.

A :class:`Plan` lists queries to create, per-frame actions (a box and corrective clicks for the
tool's assisted segmenter, or "absent") and time intervals to mark with the ``[`` / ``]`` keys.
:func:`run_plan` performs them through the page's real mouse and keyboard events, exactly as a
person would, so every mask is made by the tool and saved by its autosave. The file records
``annotator: scripted`` and ``info.method`` says how the boxes, clicks and intervals were chosen.

:func:`dnerf_plan` builds the plan used for the D-NeRF ``jumpingjacks`` and ``standup`` files:
boxes and clicks from colour rules per part (the evaluated test frames), intervals read by eye from
the training frames. Such a file is a *draft*: the session marks every query it creates ``review: "draft"``
until a person reviews it in the tool.

    python -m annotations.tool.scripted ../shared/data/dnerf/jumpingjacks annotations/scenes/dnerf/jumpingjacks.json

Needs playwright and a Chromium (``tests/browser_setup.sh``); nothing is downloaded.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

CHROMIUM = Path(os.environ.get("BENCH4D_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@dataclass
class Action:
    """One thing to do on one frame for one query."""

    frame: str
    """Scene frame name."""
    query: str
    """Query text (its masks: a time-sensitive query acts on its base)."""
    box: Optional[tuple[float, float, float, float]] = None
    """``(x0, y0, x1, y1)`` to drag with the box tool; ``None`` with no clicks = mark absent."""
    clicks: list[tuple[float, float, int]] = field(default_factory=list)
    """Corrective clicks after the box: ``(x, y, 1)`` left (object), ``(x, y, 0)`` right (not object)."""


@dataclass
class Plan:
    """A scripted session."""

    queries: list[tuple[str, str, Optional[str], Optional[str]]]
    """``(text, kind, base text or None, level or None)`` in creation order."""
    actions: list[Action]
    intervals: dict[str, list[tuple[int, int]]]
    """Time-sensitive query text -> inclusive ``time_index`` intervals to mark."""
    method: str
    """Recorded in ``info.method``."""


# ---------------------------------------------------------------------------------------------
# driving the tool
# ---------------------------------------------------------------------------------------------
class _Tool:
    def __init__(self, scene_dir: Path, out: Path, method: str):
        cmd = [sys.executable, "-m", "benchmark.cli", "annotate", str(scene_dir), "--annotations", str(out),
               "--annotator", "scripted", "--method", method, "--no-timing", "--split", "all"]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.url = None
        end = time.monotonic() + 120
        while time.monotonic() < end and self.url is None:
            line = self.proc.stdout.readline()
            if not line:
                break
            m = re.search(r"open (http://\S+)", line)
            self.url = m.group(1) if m else None
        if self.url is None:
            self.proc.kill()
            raise RuntimeError("bench4d annotate did not start")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=20)


def run_plan(plan: Plan, scene_dir: str | Path, out: str | Path, *, log: Callable[[str], None] = print) -> dict:
    """Perform ``plan`` in the tool on ``scene_dir``, saving to ``out``; returns counts and timings."""
    from playwright.sync_api import sync_playwright

    tool = _Tool(Path(scene_dir), Path(out), plan.method)
    stats = {"actions": 0, "absent": 0, "segment_ms": [], "seconds": 0.0}
    t_start = time.perf_counter()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
            ctx = browser.new_context(viewport={"width": 1400, "height": 900}, bypass_csp=True)
            ctx.route("**/*", lambda r: r.continue_() if r.request.url.startswith("http://127.0.0.1") else r.abort())
            page = ctx.new_page()
            page.goto(tool.url)
            page.wait_for_function("document.body.dataset.ready === '1'", timeout=60000)
            driver = _PageDriver(page, stats)
            driver.add_queries(plan.queries)
            page.keyboard.press("b")
            for act in plan.actions:
                driver.perform(act)
            for text, ivs in plan.intervals.items():
                driver.mark_intervals(text, ivs)
            if page.evaluate("window.bench4d.flush()") is not True:
                raise RuntimeError("the last edits were not saved")
            ctx.close()
            browser.close()
    finally:
        tool.stop()
    stats["seconds"] = time.perf_counter() - t_start
    log(f"{stats['actions']} actions ({stats['absent']} absent), median segmentation "
        f"{np.median(stats['segment_ms']) if stats['segment_ms'] else 0:.0f} ms, {stats['seconds']:.0f} s in all")
    return stats


class _PageDriver:
    """The tool's page driven through its real mouse and keyboard events; counts go into ``stats``."""

    def __init__(self, page, stats: dict):
        self.page = page
        self.stats = stats
        self.frames = page.evaluate("window.bench4d.S.frames")
        self.index = {f["name"]: f["index"] for f in self.frames}
        self.by_time: dict[int, int] = {}  # time index -> the first frame at that time
        for f in self.frames:
            self.by_time.setdefault(f["time_index"], f["index"])

    def qid(self, text: str) -> int:
        return {q["text"]: q["id"] for q in self.page.evaluate("window.bench4d.S.queries")}[text]

    def add_queries(self, queries: list[tuple[str, str, Optional[str], Optional[str]]]) -> None:
        """Create the queries the file does not hold yet, through the add-query form."""
        page = self.page
        existing = {q["text"]: q["id"] for q in page.evaluate("window.bench4d.S.queries")}
        for text, kind, base, level in queries:
            if text in existing:
                continue
            page.locator("#add-query summary").click()
            page.fill("#new-text", text)
            page.select_option("#new-kind", kind)
            if base is not None:
                page.select_option("#new-base", label=f"base: {base}")
            page.select_option("#new-level", level or "")
            n = page.evaluate("window.bench4d.S.queries.length")
            page.click("#add-query-btn")
            page.wait_for_function(f"window.bench4d.S.queries.length === {n + 1}")
            page.locator("#add-query summary").click()

    def goto(self, i: int) -> None:
        self.page.evaluate("i => window.bench4d.goto(i)", i)
        self.page.wait_for_function(f"window.bench4d.frame() === {i} && window.bench4d.S.loaded.has({i})")

    def to_page(self, x: float, y: float, w: int, h: int) -> tuple[float, float]:
        """Page coordinates of image pixel ``(x, y)`` of a ``w`` x ``h`` frame."""
        box = self.page.locator("#view").bounding_box()
        return box["x"] + x * box["width"] / w, box["y"] + y * box["height"] / h

    def wait_segment(self) -> None:
        """Wait for the segmenter's message; record its time (a failure raises)."""
        page = self.page
        page.wait_for_function("document.querySelector('#message').textContent.startsWith('grabcut') || "
                               "document.querySelector('#message').textContent.startsWith('sam') || "
                               "document.querySelector('#message').textContent.startsWith('segmentation failed')",
                               timeout=30000)
        msg = page.inner_text("#message")
        if msg.startswith("segmentation failed"):
            raise RuntimeError(msg)
        self.stats["segment_ms"].append(float(re.search(r"(\d+) ms", msg).group(1)))

    def perform(self, act: Action) -> None:
        """One action: mark absent, or drag the box and make the corrective clicks."""
        page = self.page
        i = self.index[act.frame]
        if page.evaluate("window.bench4d.frame()") != i:
            self.goto(i)
        page.evaluate("q => window.bench4d.select(q)", self.qid(act.query))
        w, h = self.frames[i]["width"], self.frames[i]["height"]
        if act.box is None and not act.clicks:
            page.locator("#view").focus()
            page.keyboard.press("a")
            self.stats["absent"] += 1
        else:
            page.evaluate("document.querySelector('#message').textContent = ''")
            x0, y0, x1, y1 = act.box
            page.mouse.move(*self.to_page(x0, y0, w, h))
            page.mouse.down()
            page.mouse.move(*self.to_page(x1, y1, w, h), steps=4)
            page.mouse.up()
            self.wait_segment()
            for x, y, lbl in act.clicks:
                page.evaluate("document.querySelector('#message').textContent = ''")
                page.mouse.click(*self.to_page(x, y, w, h), button="left" if lbl else "right")
                self.wait_segment()
        self.stats["actions"] += 1

    def mark_intervals(self, text: str, intervals: list[tuple[int, int]]) -> None:
        """Mark each inclusive interval of query ``text`` with the ``[`` and ``]`` keys."""
        self.page.evaluate("q => window.bench4d.select(q)", self.qid(text))
        for lo, hi in intervals:
            self.goto(self.by_time[lo])
            self.page.keyboard.press("[")
            self.goto(self.by_time[hi])
            self.page.keyboard.press("]")


# ---------------------------------------------------------------------------------------------
# the D-NeRF plans
# ---------------------------------------------------------------------------------------------
HSVRule = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]

DNERF_PARTS: dict[str, dict] = {
    "jumpingjacks": {
        "whole": "person",
        "parts": {  # OpenCV HSV: hue 0..180
            "orange sweater": ("part", lambda h, s, v: (h >= 5) & (h <= 20) & (s >= 110) & (v >= 80)),
            "denim shorts": ("part", lambda h, s, v: (h >= 95) & (h <= 130) & (s >= 35) & (v >= 35) & (v <= 190)),
            "yellow sneakers": ("part", lambda h, s, v: (h >= 21) & (h <= 38) & (s >= 120) & (v >= 150)),
        },
        # read by eye from the 200 training frames: hands clearly above the shoulders; arms hanging down
        "intervals": {"arms raised": [(0, 25), (177, 199)], "arms by the sides": [(56, 135)]},
    },
    "standup": {
        "whole": "worker",
        "parts": {
            "white helmet": ("part", lambda h, s, v: (s <= 70) & (v >= 115)),
            "safety vest": ("part", lambda h, s, v: ((((h <= 12) | (h >= 170)) & (s >= 150) & (v >= 120))
                                                     | ((h >= 20) & (h <= 40) & (s >= 120) & (v >= 140)))),
            "work boots": ("part", lambda h, s, v: (h >= 8) & (h <= 25) & (s >= 60) & (s <= 190) & (v >= 70)
                           & (v <= 200)),
        },
        # deep squat until about t=94; rising and then upright to the end
        "intervals": {"crouching": [(0, 94)], "standing up": [(95, 149)]},
    },
}


def _components(mask: np.ndarray, min_px: int) -> list[np.ndarray]:
    """Components of ``mask`` with at least ``min_px`` pixels, largest first."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1
    return [lab == i for i in order if stats[i, cv2.CC_STAT_AREA] >= min_px]


def _clean(mask: np.ndarray) -> np.ndarray:
    """Open then close a colour mask, and fill its holes (a logo on a sweater is the sweater)."""
    m = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    filled = np.zeros_like(m)
    cv2.drawContours(filled, contours, -1, 1, thickness=-1)
    return filled.astype(bool)


def _interior(comp: np.ndarray) -> tuple[float, float]:
    dist = cv2.distanceTransform(np.pad(comp, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return j + 0.5, i + 0.5


def part_prompt(part: np.ndarray, alpha: np.ndarray, min_px: int, pad: int = 3, max_clicks: int = 4,
                image: Optional[np.ndarray] = None, min_colour_distance: float = 30.0):
    """Box and clicks for one part: the box around its main colour components, a left click inside
    each, a right click inside each other region of the object within the box whose mean colour
    differs from the part's by more than ``min_colour_distance`` (CIELAB; with ``image``): a region
    of similar colour may be a piece of the part the colour rule missed. ``None``: not visible."""
    comps = _components(part, min_px)
    if not comps:
        return None
    keep = [c for c in comps if c.sum() >= 0.25 * comps[0].sum()][:max_clicks]
    union = np.logical_or.reduce(keep)
    h, w = part.shape
    ys, xs = np.nonzero(union)
    box = (max(0, int(xs.min()) - pad), max(0, int(ys.min()) - pad), min(w, int(xs.max()) + 1 + pad),
           min(h, int(ys.max()) + 1 + pad))
    clicks = [(*_interior(c), 1) for c in keep]
    inside = np.zeros_like(part)
    inside[box[1]:box[3], box[0]:box[2]] = True
    grown = cv2.dilate(part.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    rest = alpha & ~grown & inside
    if image is None:
        others = _components(rest, max(min_px, 60))
    else:  # dark and light regions apart (hair next to a face is two regions, two clicks)
        value = cv2.cvtColor(image, cv2.COLOR_RGB2HSV)[..., 2]
        others = _components(rest & (value < 90), max(min_px, 60)) + _components(rest & (value >= 90), max(min_px, 60))
        others.sort(key=lambda c: -int(c.sum()))
    if image is not None:
        lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
        ref = lab[union].mean(0)
        others = [c for c in others if np.linalg.norm(lab[c].mean(0) - ref) > min_colour_distance]
    clicks += [(*_interior(c), 0) for c in others[:max_clicks]]
    return box, clicks


def dnerf_plan(scene, split: str = "test", min_px: int = 40) -> Plan:
    """Boxes and clicks from colour rules (see :data:`DNERF_PARTS`) on ``split`` frames of ``scene``."""
    spec = DNERF_PARTS[scene.name]
    whole = spec["whole"]
    queries = [(whole, "agnostic", None, "whole")]
    queries += [(text, "agnostic", None, level) for text, (level, _) in spec["parts"].items()]
    queries += [(text, "sensitive", whole, None) for text in spec["intervals"]]
    actions = []
    for frame in scene.split(split):
        img = (np.clip(frame.image(), 0, 1) * 255 + 0.5).astype(np.uint8)
        alpha = frame.alpha()
        h, w = alpha.shape
        ys, xs = np.nonzero(alpha)
        pad = 4
        actions.append(Action(frame.name, whole, (max(0, xs.min() - pad), max(0, ys.min() - pad),
                                                  min(w, xs.max() + 1 + pad), min(h, ys.max() + 1 + pad))))
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV).astype(np.int32)
        for text, (_, rule) in spec["parts"].items():
            part = _clean(rule(hsv[..., 0], hsv[..., 1], hsv[..., 2]) & alpha) & alpha
            prompt = part_prompt(part, alpha, min_px, image=img)
            if prompt is not None:  # no matching colour: left "not annotated" (never scored), not "absent"
                actions.append(Action(frame.name, text, prompt[0], prompt[1]))
    method = ("scripted session in the tool: per part, a box around the part's colour-rule components, a left "
              "click inside each and a right click inside each other region of the object in the box "
              "(annotations/tool/scripted.py), masks by the tool's GrabCut; whole object from a box around the "
              "D-NeRF alpha; parts with no matching colour left not annotated; time intervals read by eye from the "
              "training frames by eye, without the truth (edges uncertain by a few frames). A draft: review by hand.")
    return Plan(queries, actions, {k: list(v) for k, v in spec["intervals"].items()}, method)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m annotations.tool.scripted", description=__doc__.splitlines()[0])
    ap.add_argument("scene_dir")
    ap.add_argument("out", type=Path)
    args = ap.parse_args(argv)
    from benchmark.loaders import load_scene

    scene = load_scene(args.scene_dir)
    if scene.name not in DNERF_PARTS:
        ap.error(f"no plan for scene {scene.name!r} (known: {', '.join(DNERF_PARTS)})")
    run_plan(dnerf_plan(scene), args.scene_dir, args.out)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
