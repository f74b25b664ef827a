"""A small sample of the fault-injection suite (tests/fault_injection.py; the large one is its command,
docs/guarantees.md): bit flips, truncations, links, full disks, signals, special files at every depth,
damaged kernels, pickled payloads, resumes under other numerics, forged records and copied folders on
both learner families, none
misreported, escaped or hung."""

from __future__ import annotations

import pytest


@pytest.mark.slow
def test_a_sample_of_faults_on_every_family_is_refused_or_survived_exactly(tmp_path):
    from tests.fault_injection import FAMILIES, run, table

    counts, failures = run(trials=24, signals=2, seed=50, families=list(FAMILIES), work=tmp_path,
                           signal_episodes=30)
    assert not failures, "\n".join(failures) + "\n" + table(counts)
    tried = {(family, kind) for family, kind, _ in counts}
    for family in FAMILIES:
        assert {kind for f, kind in tried if f == family} >= {"flip", "truncate", "link", "disk", "signal", "special",
                                                              "kernel", "pickle", "numerics", "record",
                                                              "copy"}, table(counts)
    assert sum(v for (_, _, outcome), v in counts.items() if outcome == "refused") > 10
    assert sum(v for (_, _, outcome), v in counts.items() if outcome == "exact") > 3


def test_the_documented_command_runs_at_a_tiny_size(capsys):
    from pathlib import Path

    from tests.fault_injection import main

    guarantees = (Path(__file__).resolve().parent.parent / "docs" / "guarantees.md").read_text()
    assert "    python -m tests.fault_injection --trials 400 --signals 12\n" in guarantees
    assert main(["--trials", "3", "--signals", "0", "--families", "spg"]) == 0
    out = capsys.readouterr().out
    assert "| all | all | 3 |" in out and out.rstrip().endswith("| 0 |")
