"""Puts this folder on ``sys.path``, so that the op families' test folders import the shared cases by name
(``from skeletal_cases import make_case``): the tests have no ``__init__.py`` files (pytest's default import mode)."""
import sys
from pathlib import Path

_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
