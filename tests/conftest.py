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
