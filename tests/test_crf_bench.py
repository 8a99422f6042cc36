"""`topseg bench crf` end to end on the stand-in unaries (one frame: exact takes ~1.5 s)."""

from __future__ import annotations

import json

from topseg.services.cli import main


def test_bench_crf_reports_the_required_figures(capsys):
    code = main(
        ["-q", "bench", "crf", "--unaries", "synthetic", "--frames", "1", "--repeat", "2", "--json"]
    )
    assert code == 0
    figures = json.loads(capsys.readouterr().out)
    for key in ("crf_exact_ms_per_frame", "crf_realtime_ms_per_frame", "crf_energy_ratio"):
        assert figures[key] > 0
    assert figures["crf_energy_ratio"] <= 1.02
    assert 0.5 <= figures["crf_gain_fraction"] <= 1.0 + 1e-9
    assert figures["frame_shape"] == "640x480"
    assert "synthetic" in figures["unaries"]


def test_bench_crf_prints_a_table(capsys):
    code = main(["-q", "bench", "crf", "--unaries", "synthetic", "--frames", "1", "--repeat", "1"])
    assert code == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "topseg bench crf"
    assert any(line.startswith("crf_realtime_ms_per_frame") for line in out)
