"""`benchmarks/peers.py`: reading the peers' script's figures, and failing clearly without them.

The real peers need Numba and Taichi (not jaxmotion dependencies), so these tests run the
driver against stand-in scripts that print what perf-lab's `bench_peers.py` prints."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import peers as peers_benchmark

# Lines in the format bench_peers.py prints (evals/s from a run on 2026-12-05).
REAL_LINES = """\
{"kind": "meta", "run_id": "20261205-085712"}
bench numba_simd64     B=  100 evals/s    5109.3  M ctrl-steps/s   25.55  compile   7.03s  reps 5
bench numba_simd64     B= 1000 evals/s    6291.8  M ctrl-steps/s   31.46  compile   0.00s  reps 5
bench taichi_kernel    B=  100 evals/s    1705.0  M ctrl-steps/s    8.53  compile   1.52s  reps 5
bench taichi_kernel    B= 1000 evals/s    3194.4  M ctrl-steps/s   15.97  compile   0.00s  reps 5
"""


def _fake_lab(tmp_path, body: str) -> Path:
    lab = tmp_path / "perf-lab"
    (lab / "peers").mkdir(parents=True)
    (lab / "peers" / "bench_peers.py").write_text(body)
    return lab


def test_peers_reads_every_implementation_and_batch(tmp_path):
    lab = _fake_lab(tmp_path, f"print({REAL_LINES!r})\n")
    rates = peers_benchmark.peers(sys.executable, lab, ["numba_simd64", "taichi_kernel"])
    assert rates == {
        "numba_simd64": {100: 5109.3, 1000: 6291.8},
        "taichi_kernel": {100: 1705.0, 1000: 3194.4},
    }


def test_peers_runs_on_a_copy_and_leaves_the_lab_untouched(tmp_path):
    # The real script appends to results.jsonl beside itself.
    body = (
        "import pathlib\n"
        "pathlib.Path(__file__).with_name('results.jsonl').write_text('x')\n"
        f"print({REAL_LINES!r})\n"
    )
    lab = _fake_lab(tmp_path, body)
    peers_benchmark.peers(sys.executable, lab, ["numba_simd64"])
    assert not (lab / "peers" / "results.jsonl").exists()


def test_a_missing_peer_or_a_failing_script_is_reported_with_what_to_install(tmp_path):
    lab = _fake_lab(tmp_path, "import numba_that_is_not_installed\n")
    with pytest.raises(SystemExit, match="numba, taichi and scipy"):
        peers_benchmark.peers(sys.executable, lab, ["numba_simd64"])
    lab = _fake_lab(tmp_path / "other", f"print({REAL_LINES!r})\n")
    with pytest.raises(SystemExit, match="no figures for warp_kernel"):
        peers_benchmark.peers(sys.executable, lab, ["numba_simd64", "warp_kernel"])


def test_span_prints_a_range_or_one_figure():
    assert peers_benchmark.span([5109.3, 5545.2]) == "5,109-5,545"
    assert peers_benchmark.span([3194.4, 3194.2]) == "3,194"
