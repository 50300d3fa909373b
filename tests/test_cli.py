import subprocess
import sys

from torchsfm.cli import main
from torchsfm.demo import run_demo


def test_demo_runs_on_the_bundled_sample(capsys):
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    assert "Merton College I" in out and "0-1" in out and "1-2" in out


def test_demo_recovers_the_ground_truth():
    for pair in run_demo(outliers=0.4, seed=0):
        assert pair.rotation_error_deg < 0.5 and pair.translation_error_deg < 2.0
        assert pair.recall > 0.97 and pair.precision > 0.99
        assert pair.reprojection_rms_px < 0.5


def test_errors_are_one_line_and_a_nonzero_exit(capsys):
    assert main(["demo", "--outliers", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "torchsfm: error: outliers must lie in [0, 1), got 2.0"


def test_module_entry_point():
    result = subprocess.run([sys.executable, "-m", "torchsfm", "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "demo" in result.stdout
