"""The paper re-run's plan (meshseal.evaluation.paper_plan, run by experiments/paper.py): shards split the
re-run without training a run twice or apart from the run it starts from (no training here)."""

import argparse
from pathlib import Path

from meshseal.evaluation import paper_plan as paper
from meshseal.training.train import TrainConfig

ROOT = Path(__file__).resolve().parent.parent


def _plan(shard, seeds=(0, 1)):
    args = argparse.Namespace(seeds=list(seeds), runs=3, tables=list(range(1, 10)), out=Path("OUT"), budget=150,
                              shard=shard)
    base = TrainConfig.load(ROOT / "configs" / "seed_protocol8.yaml")
    return base, [(seed, table, row, bits) for seed, table, row, bits, group in paper.plan(args, base)
                  if group % shard[1] == shard[0]]


def test_shards_cover_the_plan_once_and_keep_a_run_with_its_start():
    base, whole = _plan((0, 1))
    key = lambda s, t, r, b: paper.planned(Path("OUT"), base, t, r, b, 150, s)[0]  # noqa: E731
    shards = [{key(*run) for run in _plan((k, 5))[1]} for k in range(5)]
    assert set().union(*shards) == {key(*run) for run in whole}
    assert sum(len(s) for s in shards) == len(set().union(*shards))  # no run trained by two shards
    for seed, table, row, bits in whole:
        if row.start_from:
            source = next(r for r in table.rows if r.label == row.start_from)
            assert any({key(seed, table, row, bits), key(seed, table, source, bits)} <= s for s in shards)


def test_the_surface_code_row_trains_nothing_and_reads_the_papers_pictures():
    base, whole = _plan((0, 1), seeds=(2,))
    rows = [(seed, table, row, bits) for seed, table, row, bits in whole if row.label == paper.SURFACE_ROW]
    assert [bits for *_, bits in rows] == list(paper.BITS)
    for seed, table, row, bits in rows:
        config = paper.planned(Path("OUT"), base, table, row, bits, 150, seed)[1]
        assert config.train.steps == 0 and config.model.decoder == "surface" and config.model.pattern_seed == seed
        assert config.model.chips > bits
