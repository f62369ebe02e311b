import json
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="session")
def paper_counts() -> dict:
    """The paper's counts (Holmes-Cerfon 2016, Tables 1 and 3), carried with the tests."""
    return json.loads((DATA / "paper_counts.json").read_text())
