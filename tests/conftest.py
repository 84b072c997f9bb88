import os

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def paper():
    from testbed import scenario

    return scenario.load("paper")
