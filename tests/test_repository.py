"""Checks on the repository as a user meets it: the demo's code path and table, the README's size and its
activation line, and no words about how the project is developed in what the repository ships."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

README_LIMIT = 16 * 1024
"""Bytes the README may hold: a user reads it in one sitting."""

DEVELOPMENT_PHRASES: dict[str, str] = {
    "a work session": r"\b(previous|prior|earlier|last|next|later|future|this) sessions?\b",
    "a numbered session": r"\bsessions?\s*#?\s*\d+",
    "an issue number": r"\bissues?\s*#",
    "a closing reference": r"\b(fixes|closes|resolves)\s+#\d+",
    "an agent": r"(?<!user[- ])\bagents?\b",
    "a filed report": (r"\bfiled\s+(as\s+)?(an?\s+|the\s+)?(issue|bug|ticket|report)s?\b"
                       r"|\b(issue|bug|ticket)s?\s+(was\s+|were\s+|is\s+|are\s+|been\s+)?filed\b"),
    "a TODO naming the work process": r"\b(TODO|FIXME)\s*\(\s*(session|issue|agent)",
    "a change narrative": (r"\bwe\s+(changed|switched|rewrote|refactored|renamed)\b"
                           r"|\bprevious version of (the|this) (code|function|module|file|test)\b"),
}
"""Phrases about how the project is developed (label -> case-insensitive pattern). Phrases, not bare
words: an HTTP session, the annotation tool's session module, a browser's User-Agent or results
"filed under" a dataset are what the code is about."""

PATTERNS = {label: re.compile(pattern, re.IGNORECASE) for label, pattern in DEVELOPMENT_PHRASES.items()}

SCANNED_EXCLUDED = ("reports/",)
"""Path prefixes not scanned: reports/ is the measurement record, where dated history belongs."""

THIS_FILE = Path(__file__).resolve().relative_to(ROOT).as_posix()


def development_words(text: str) -> list[tuple[int, str, str]]:
    """``(line number, label, matched text)`` of every development phrase in ``text``."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        for label, pattern in PATTERNS.items():
            found += [(number, label, m.group(0)) for m in pattern.finditer(line)]
    return found


def shipped_files() -> list[str]:
    """Tracked files, and new files git does not ignore, outside :data:`SCANNED_EXCLUDED`."""
    try:
        out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                             capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as err:
        pytest.skip(f"not a git checkout ({err})")
    return sorted({p for p in out.splitlines() if p and not p.startswith(SCANNED_EXCLUDED) and p != THIS_FILE})


def test_no_development_words_in_shipped_files():
    hits = []
    for rel in shipped_files():
        path = ROOT / rel
        if not path.is_file():
            continue  # deleted in the working tree
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue  # images and other binary files
        hits += [f"{rel}:{line}: {label}: {matched!r}" for line, label, matched in development_words(text)]
    assert not hits, "words about how the project is developed:\n" + "\n".join(hits)


@pytest.mark.parametrize("planted", [
    "# fixed in the previous session",
    "    # TODO(session " + "14): measure again",  # split: the repository's own checks scan this file too
    '"""Kept as issue #12 asks."""',
    "see issue #",
    "a helper agent wrote this",
    "the agent's report",
    "filed as an issue",
    "a bug was filed against the loader",
    "We changed the threshold here.",
    "Closes #31",
])
def test_a_planted_development_line_is_found(planted):
    assert development_words(f"x = 1\n{planted}\n"), planted
    assert development_words(f"x = 1\n{planted}\n")[0][0] == 2


@pytest.mark.parametrize("legitimate", [
    "the annotation session holds a lock on the file",
    "the annotation set is open in another session",
    "from annotations.tool.session import AnnotationSession",
    "a scripted session in the tool",
    "requests.Session() keeps the HTTP session alive",
    "the server checks the User-Agent header",
    "the dataset results are filed under",
    "a session-scoped fixture",
    "the issue of scale: a tiny part",
])
def test_legitimate_uses_are_not_flagged(legitimate):
    assert development_words(legitimate) == []


def test_readme_is_short_and_tells_how_to_activate_the_environment():
    readme = (ROOT / "README.md").read_bytes()
    assert len(readme) < README_LIMIT, f"README.md is {len(readme)} bytes (limit {README_LIMIT})"
    assert b"source .venv/bin/activate" in readme


def test_make_demo_ends_by_telling_how_to_put_bench4d_on_the_path():
    recipe = re.search(r"^demo:.*\n((?:\t.*\n)+)", (ROOT / "Makefile").read_text(), re.MULTILINE)
    assert recipe, "Makefile has no demo target"
    steps = recipe.group(1).splitlines()
    assert "bench4d demo" in "\n".join(steps)
    assert "source $(VENV)/bin/activate" in steps[-1] and steps[-1].lstrip("\t@").startswith("echo")


TINY_DEMO = [arg for option in ("geometry.static_iterations=20", "geometry.deformation_iterations=20",
                                 "field.iterations=30", "autoencoder.min_steps=60", "autoencoder.max_steps=60",
                                 "status.static_iterations=20", "status.iterations=30",
                                 "caption_autoencoder.min_steps=60", "caption_autoencoder.max_steps=60")
             for arg in ("--set", option)]
"""Demo options that fit the 4D method in seconds on the smoke preset."""


def test_every_demo_schedule_is_an_option_of_the_demo_method():
    # an override the method does not have would be dropped, and the demo would fit at full size
    from benchmark.commands.demo import DEMO_METHOD, DEMO_OVERRIDES, method_overrides

    assert method_overrides([DEMO_METHOD], {})[DEMO_METHOD] == DEMO_OVERRIDES


def _table_rows(out: str) -> dict[str, list[str]]:
    """The demo table's rows (first cell -> the other cells), read from the command's output."""
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(("method ", "split ")) and "% of ceiling" in line)
    by_split = lines[start].startswith("split ")
    rows = {}
    for line in lines[start + 1:]:
        if not line.strip():
            break
        cells = re.split(r"\s{2,}", line.strip())
        if by_split and not cells[0].startswith("perfect features"):  # "<split>/<method>" -> the other cells
            cells = [f"{cells[0]}/{cells[1]}"] + cells[2:]  # a ceiling row of each split too
        rows[cells[0]] = cells[1:]
    return rows


def test_demo_fits_the_4d_method_and_the_floor_and_shows_their_share_of_the_ceiling(tmp_path, capsys):
    from benchmark.cli import main

    cache = tmp_path / "cache"
    assert main(["demo", "--scene", "smoke", "--size", "32", "--cache-dir", str(cache), "--quiet", *TINY_DEMO]) == 0
    out = capsys.readouterr().out
    rows = _table_rows(out)
    shown = ("4d-langsplat", "nearest-frame (2D floor)", "nearest-frame-masks (2D floor)")
    # both splits, each answered by the one fit of each method: the paper's and the novel views
    keys = [f"{split}/{m}" for split in ("paper", "novel-view") for m in shown]
    ceilings = [f"{split}/perfect features (ceiling)" for split in ("paper", "novel-view")]
    assert set(rows) == {*keys, *ceilings}, rows
    for method in keys:
        mIoU, acc, viou, share = rows[method][:4]
        assert re.fullmatch(r"\d+ / \d+", share), share  # share of the ceiling's mIoU / vIoU, in percent
        # each split's runs against the ceiling of that split's own frames
        ceiling = float(rows[f"{method.split('/')[0]}/perfect features (ceiling)"][0])
        assert int(share.split(" / ")[0]) == round(100 * float(mIoU) / ceiling)
    assert all(rows[c][3] == "100 / 100" for c in ceilings)
    assert "not the leaderboard's" in out
    # the results lie in the cache: a demo never writes the committed results/
    results = cache / "demo-results" / "synthetic" / "smoke"
    assert (results / "4d-langsplat" / "oracle" / "seed0.json").is_file()
    assert (results / "nearest-frame" / "oracle" / "seed0.json").is_file()
    # the README's scoring example reads what the demo leaves (here at the test's scene and size)
    gt, pred = readme_score_example()
    assert main(["score", "--gt", str(demo_path(gt, cache, "smoke", 32)),
                 "--pred", str(demo_path(pred, cache, "smoke", 32))]) == 0
    assert "mean over 1 scene(s)" in capsys.readouterr().out

    assert main(["demo", "--scene", "smoke", "--size", "32", "--cache-dir", str(cache), "--quiet",
                 "--method", "nearest-frame"]) == 0
    assert set(_table_rows(capsys.readouterr().out)) == {"paper/nearest-frame (2D floor)",
                                                         "novel-view/nearest-frame (2D floor)",
                                                         "paper/perfect features (ceiling)",
                                                         "novel-view/perfect features (ceiling)"}
    assert main(["demo", "--scene", "smoke", "--size", "32", "--cache-dir", str(cache), "--quiet",
                 "--set", "no_such_option=1"]) == 2
    assert "no_such_option" in capsys.readouterr().err


def readme_score_example() -> tuple[str, str]:
    """(--gt, --pred) of the README's first ``bench4d score`` command (a line may continue with ``\\``)."""
    text = (ROOT / "README.md").read_text().replace("\\\n", " ")
    command = next(line for line in text.splitlines() if line.startswith("bench4d score --gt cache/"))
    args = command.split()
    return args[args.index("--gt") + 1], args[args.index("--pred") + 1]


def demo_path(path: str, cache: Path, scene: str, size: int) -> Path:
    """A README path under ``cache/`` as the demo of ``scene`` at ``size`` px in ``cache`` leaves it."""
    from benchmark.commands.demo import DEMO_SIZE, default_preset

    preset = default_preset()
    assert path.startswith("cache/") and (f"/{DEMO_SIZE}px/{preset}/" in path or f"/{preset}/" in path), path
    return cache / path.removeprefix("cache/").replace(f"{DEMO_SIZE}px", f"{size}px").replace(f"/{preset}/", f"/{scene}/")


def test_the_readme_scoring_example_names_the_demos_own_scene_and_method():
    from benchmark.commands.demo import DEMO_METHOD, DEMO_SIZE, default_preset

    gt, pred = readme_score_example()
    assert gt == f"cache/scenes/{DEMO_SIZE}px/{default_preset()}/annotations.json"
    assert pred.startswith(f"cache/demo-results/synthetic/{default_preset()}/{DEMO_METHOD}/oracle/seed0")


def test_demo_table_without_a_ceiling_shows_no_share():
    from benchmark.commands.demo import demo_table

    run = {"method": "m", "metrics": {"mIoU": 40.0, "agnostic_queries": 3},
           "timing": {"fit_seconds": 2.0, "query_agnostic": {"seconds_per_frame": 0.05}}}
    assert demo_table([run], {"mIoU": 80.0, "vIoU": float("nan")}, set())[1].split() == ["m", "40.0", "50", "2.0", "50"]
    assert demo_table([run], None, set())[1].split() == ["m", "40.0", "–", "2.0", "50"]
