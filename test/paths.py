"""Where the tests find the repository's files, whichever folder of test/ they are in."""

from pathlib import Path

TESTS = Path(__file__).resolve().parent
DATA = TESTS / 'data'
REPO = TESTS.parent
CONFIG = REPO / 'config'
