import atexit
import os
import shutil
import tempfile

import pytest

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
    """The test FMU of the Lienard plant (tests/fmu: C source built with gcc against fmpy's FMI headers)."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("testbed_test_fmu_build", Path(__file__).parent / "fmu" / "build.py")
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
