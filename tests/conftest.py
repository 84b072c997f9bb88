import atexit
import os
import secrets
import shutil
import sys
import tempfile

import pytest
from helpers.live import LOGS
from helpers.procs import cmdlines, procs_with, reap

os.environ.setdefault("MPLBACKEND", "Agg")
# live runs record by default: the tests' recordings go to a scratch directory, not recordings/
_REC_DIR = tempfile.mkdtemp(prefix="testbed-test-recordings-")
os.environ["TESTBED_RECORDINGS_DIR"] = _REC_DIR
atexit.register(shutil.rmtree, _REC_DIR, True)


@pytest.fixture(scope="session")
def paper():
    from testbed import scenario

    return scenario.load("paper")


@pytest.fixture(scope="session")
def lienard_fmu(tmp_path_factory):
    """The test FMU of the Lienard plant (tests/data/fmu: C source built with gcc against fmpy's FMI headers)."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("testbed_test_fmu_build", Path(__file__).parent / "data" / "fmu" / "build.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    return build.build(tmp_path_factory.mktemp("fmu") / "lienard.fmu")


def pytest_configure(config):
    """An unknown name in ``TESTBED_REQUIRE`` is a usage error (a typo must not make a capability optional)."""
    from failclosed import required

    required()


def pytest_report_header(config):
    from failclosed import REQUIRE_ENV, required

    req = required()
    return f"{REQUIRE_ENV}: {', '.join(sorted(req)) if req else 'none (a missing capability skips with its reason)'}"


@pytest.fixture(scope="session", autouse=True)
def _node_logs(request):
    """Node logs of runs with faults go to one directory, removed after the session (kept if a test failed)."""
    yield
    if request.session.testsfailed and os.listdir(LOGS):
        print(f"\nnode logs of the live runs kept in {LOGS}", file=sys.stderr)
    else:
        shutil.rmtree(LOGS, ignore_errors=True)


@pytest.fixture
def run_id():
    rid = f"t{os.getpid()}x{secrets.token_hex(4)}"
    yield rid
    left = procs_with(rid)
    names = cmdlines(left)
    left = reap(rid)
    assert not left, f"orphan processes of run {rid}: {names}"
