"""``bench4d ablate states`` (the paper's Table 5): the table over K and seeds, read back from kept runs."""

from __future__ import annotations

import json

import pytest

from benchmark.studies import states


def _kept(results_dir, k: int, seed: int, acc: float, viou: float) -> None:
    """A complete results file of the states study's (K, seed) run (the schema's full example, adapted)."""
    from benchmark.core.protocol import PROTOCOLS
    from benchmark.results import results_path, write_results
    from test_results_schema import good_doc

    doc = good_doc()
    doc.pop("format"), doc.pop("version")
    doc.update(method="4d-langsplat", scene="chickchicken", seed=seed, split="paper",
               method_config={"status": {"num_states": k}, "extensions": {"choose_states": False}},
               protocol=PROTOCOLS["release"].to_dict(), fit={"key": f"k{k}s{seed}", "cached": False})
    doc["metrics"] = {**doc["metrics"], "Acc": acc, "vIoU": viou}
    write_results(results_path(results_dir / "ablations" / f"states-k{k}", "synthetic", "chickchicken",
                               "4d-langsplat", "oracle", seed), doc)


def test_the_states_table_reads_kept_runs_and_gives_the_seed_spread(tmp_path, monkeypatch):
    def no_evaluation(options):
        raise AssertionError(f"evaluated K={options.method_options['status.num_states']} seed {options.seed}")

    monkeypatch.setattr(states, "evaluate", no_evaluation)
    for seed, (acc2, acc3) in enumerate([(90.0, 100.0), (80.0, 90.0), (70.0, 95.0)]):
        _kept(tmp_path / "results", 2, seed, acc2, 40.0 + seed)
        _kept(tmp_path / "results", 3, seed, acc3, 50.0)
    report = states.states_report("chickchicken", [2, 3], seeds=[0, 1, 2], results_dir=tmp_path / "results",
                                  cache_dir=tmp_path / "cache", size=128, out=tmp_path / "out", reuse=True)
    assert "| 2 | 80.00 ± 10.00 | 41.00 ± 1.00 |" in report.table
    assert "| 3 | 95.00 ± 5.00 | 50.00 ± 0.00 |" in report.table
    assert "protocol release" in report.table
    doc = json.loads((tmp_path / "out" / "states-chickchicken.json").read_text())
    assert [row["K"] for row in doc["rows"]] == [2, 3] and doc["rows"][0]["Acc"] == pytest.approx(80.0)
    with pytest.raises(AssertionError, match="evaluated K=2 seed 0"):  # a kept run of other options is not read
        states.states_report("chickchicken", [2], seeds=[0], results_dir=tmp_path / "results",
                             cache_dir=tmp_path / "cache", size=128, out=tmp_path / "out", reuse=True,
                             overrides={"status.iterations": "2000"})
    with pytest.raises(AssertionError, match="evaluated K=4 seed 0"):  # a missing run is evaluated
        states.states_report("chickchicken", [4], seeds=[0], results_dir=tmp_path / "results",
                             cache_dir=tmp_path / "cache", size=128, out=tmp_path / "out", reuse=True)


def test_the_paper_tables_states_section_reads_every_seed_and_calls_overlapping_k_a_tie(tmp_path):
    from benchmark.core.errors import InputError
    from benchmark.paper_tables import _states_runs, _states_table
    from benchmark.results import find_results
    from methods.registry import paper_reference

    results = tmp_path / "results"
    for seed, (acc2, acc3) in enumerate([(90.0, 100.0), (80.0, 90.0), (70.0, 95.0)]):
        _kept(results, 2, seed, acc2, 40.0 + seed)
        _kept(results, 3, seed, acc3, 50.0)
    runs = _states_runs(results, protocol="release", track="oracle", split="paper", allow_dirty=False)
    assert sorted(zip(runs["num_states"], runs["seed"])) == [(k, s) for k in (2, 3) for s in (0, 1, 2)]
    text = "\n".join(_states_table(runs, paper_reference().ablations))
    assert "| 2 | 94.56 / 88.05 | 80.00 ± 10.00 / 41.00 ± 1.00 |" in text  # every seed, not the last one read
    assert "seeds 0 1 2, protocol release, track oracle, split paper" in text
    assert "no single best, K = 2, 3 tied" in text  # 80 [55.2, 104.8] and 95 [82.6, 107.4] overlap
    separated = runs.assign(Acc=runs["seed"] / 10 + runs["num_states"].map({2: 50.0, 3: 99.0}))
    assert "ours: K = 3._" in "\n".join(_states_table(separated, paper_reference().ablations))
    # a run from a changing checkout is refused, unless allowed
    path = next(p for p in find_results(results / "ablations" / "states-k3"))
    doc = json.loads(path.read_text())
    doc["environment"] = {**doc.get("environment", {}), "git": {"commit": "abc", "dirty": True}}
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="uncommitted code"):
        _states_runs(results, protocol="release", track="oracle", split="paper", allow_dirty=False)
    assert len(_states_runs(results, protocol="release", track="oracle", split="paper", allow_dirty=True)) == 6
