"""requirements.lock: what `make test` installs is what the lock pins, and the checker sees a difference."""
from pathlib import Path

from tools.check_lock import mismatches, pinned_versions

LOCK = Path(__file__).resolve().parents[1] / "requirements.lock"


def test_the_environment_holds_the_locked_versions():
    pins = pinned_versions(LOCK)
    assert {"numpy", "proxsuite", "eclipse-zenoh", "gtsam", "casadi"} <= set(pins)
    assert mismatches(LOCK) == []


def test_a_version_other_than_the_locked_one_is_named(tmp_path):
    lock = tmp_path / "requirements.lock"
    lock.write_text("numpy==0.0.1 \\\n    --hash=sha256:00\nnot-a-package-here==1.0\n")
    problems = mismatches(lock)
    assert any(p.startswith("numpy: installed ") and "lock 0.0.1" in p for p in problems)
    assert any(p.startswith("not-a-package-here: not installed") for p in problems)
