"""The physics tests again in single precision (Taichi initialises once per process, so they
run in a child pytest with --precision f32; tolerances follow the precision)."""
import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_engine_and_bond_physics_hold_in_f32(precision):
    if precision == "f32":
        pytest.skip("already running in f32")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--precision", "f32",
                        str(ROOT / "tests" / "test_engine.py"), str(ROOT / "tests" / "test_bonds.py")],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=1200)
    tail = "\n".join(r.stdout.splitlines()[-25:])
    assert r.returncode == 0, f"f32 physics tests failed:\n{tail}\n{r.stderr[-2000:]}"
    assert " passed" in tail and "failed" not in tail
