"""`slam demo` runs the pipeline on the bundled Intel log and prints the relation table with published numbers."""

from __future__ import annotations

import pytest

from slam.cli import main

pytestmark = pytest.mark.xdist_group("pipeline")


def test_demo_quick_run_prints_relation_table(tmp_path, capsys):
    """A 300-scan demo writes the outputs and prints ours beside Cartographer's and Graph Mapping's figures;
    the relations inside the processed stretch are used and the others are counted, not dropped silently."""
    out = tmp_path / "demo"
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--out", str(out), "--max-scans", "300", "--quiet"])
    assert exc.value.code in (0, None)
    text = capsys.readouterr().out
    assert "dataset: Intel" in text and "Cartographer" in text and "0.0229" in text
    used = int(text.split("relations used: ")[1].split()[0])
    assert 0 < used < 2984 and "(of 2984;" in text
    assert (out / "trajectory.tum").exists() and (out / "map.png").exists()
