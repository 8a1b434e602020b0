import subprocess
import sys

import pytest

import thermogrammetry
from thermogrammetry.enums import StrChoice
from thermogrammetry.errors import ConfigError, InvalidInputError, ThermogrammetryError
from thermogrammetry._validate import as_points
from thermogrammetry.errors import NonFiniteError, ShapeError


def test_version_cli():
    out = subprocess.run([sys.executable, "-m", "thermogrammetry", "--version"], capture_output=True, text=True)
    assert out.returncode == 0
    assert out.stdout.strip() == f"thermogrammetry {thermogrammetry.__version__}"


class Unit(StrChoice):
    KELVIN = "K"
    CELSIUS = "C"


def test_choice_case_insensitive_and_lists_valid():
    assert Unit("c") is Unit.CELSIUS
    assert Unit("kelvin") is Unit.KELVIN
    with pytest.raises(ConfigError, match=r"'F' is not a valid Unit; expected one of 'K', 'C'"):
        Unit("F")


def test_error_tree_builtin_bases():
    assert issubclass(InvalidInputError, ValueError)
    assert issubclass(InvalidInputError, ThermogrammetryError)


def test_as_points_names_bad_value():
    with pytest.raises(ShapeError, match=r"pts: expected shape \(N, 3\), got \(4, 2\)"):
        as_points([[0, 0]] * 4, "pts", 3)
    with pytest.raises(NonFiniteError, match=r"pts: 1 non-finite value\(s\), first at index \(1, 2\)"):
        as_points([[0, 0, 0], [1, 1, float("nan")]], "pts", 3)
