"""Check that this environment holds exactly the versions pinned in requirements.lock.

`make test` and CI run it after installing, so a fresh clone tests what was tested before it; it
exits 1 and names every package whose installed version differs (or is missing).
"""
import re
import sys
from importlib import metadata
from pathlib import Path

PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;\\]+)")


def pinned_versions(lock_path: Path) -> dict[str, str]:
    pins = {}
    for line in lock_path.read_text().splitlines():
        match = PIN.match(line)
        if match:
            pins[_canonical(match.group(1))] = match.group(2)
    return pins


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def mismatches(lock_path: Path) -> list[str]:
    problems = []
    for name, wanted in sorted(pinned_versions(lock_path).items()):
        try:
            installed = metadata.version(name)
        except metadata.PackageNotFoundError:
            problems.append(f"{name}: not installed (lock: {wanted})")
            continue
        if installed != wanted:
            problems.append(f"{name}: installed {installed}, lock {wanted}")
    return problems


def main() -> int:
    lock_path = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "requirements.lock")
    problems = mismatches(lock_path)
    for problem in problems:
        print(f"check_lock: {problem}", file=sys.stderr)
    if problems:
        print(f"check_lock: {len(problems)} package(s) differ from {lock_path.name}; `make clean test` reinstalls",
              file=sys.stderr)
        return 1
    print(f"check_lock: {len(pinned_versions(lock_path))} packages as pinned in {lock_path.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
