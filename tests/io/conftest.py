"""The shared simulated acquisition of the format tests (see ``scan_helpers.py``)."""

import pytest

from scan_helpers import RawScan, simulate_raw_scan


@pytest.fixture(scope="session")
def raw_scan() -> RawScan:
    return simulate_raw_scan()
