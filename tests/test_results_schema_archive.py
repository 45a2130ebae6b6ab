"""Archiving a replaced results file never loses one: two archivings under one label (one second) both stay."""
import json

from benchmark.results import ARCHIVE_DIR, archive_results


def test_two_archivings_under_one_label_keep_both_files(tmp_path):
    root = tmp_path / "results"
    path = root / "synthetic" / "smoke" / "m" / "oracle" / "seed0.json"
    kept = []
    for value in (1, 2):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"v": value}))
        kept.append(archive_results(path, root, "config-2026-11-30T085028"))
    assert kept[0] != kept[1] and kept[1].parent.parts[-5] == "config-2026-11-30T085028-2"
    assert [json.loads(p.read_text())["v"] for p in kept] == [1, 2]
    assert (root / ARCHIVE_DIR).is_dir() and not path.exists()
