"""The validation helpers name the argument and refuse what they should."""
import math

import pytest

from torch_ao.checks import check_bool, check_choice, check_float, check_int


def test_check_int():
    assert check_int("n", 3, 1) == 3
    for bad in (True, 2.0, "3", 0):
        with pytest.raises(ValueError, match=r"^n: expected an integer"):
            check_int("n", bad, 1)
    with pytest.raises(ValueError, match=r"n: expected an integer <= 4, got 5"):
        check_int("n", 5, 1, 4)


def test_check_float():
    assert check_float("tau", 1, 0, open_minimum=True) == 1.0
    with pytest.raises(ValueError, match=r"tau: expected a number > 0, got 0.0"):
        check_float("tau", 0.0, 0, open_minimum=True)
    with pytest.raises(ValueError, match="tau: expected a finite number"):
        check_float("tau", math.inf)
    assert check_float("r", math.inf, 0, finite=False) == math.inf
    with pytest.raises(ValueError, match="r: expected a finite number"):
        check_float("r", math.nan, finite=False)
    with pytest.raises(ValueError, match="e: expected a number < 1"):
        check_float("e", 1.0, 0, 1, open_maximum=True)
    with pytest.raises(ValueError, match="b: expected a number"):
        check_float("b", False)


def test_check_choice_and_bool():
    assert check_choice("fetch", "nearest", ("nearest", "bilinear")) == "nearest"
    with pytest.raises(ValueError, match=r"fetch: expected one of \('nearest', 'bilinear'\), got 'cubic'"):
        check_choice("fetch", "cubic", ("nearest", "bilinear"))
    assert check_bool("jitter", False) is False
    with pytest.raises(ValueError, match="jitter: expected True or False, got 1"):
        check_bool("jitter", 1)


def test_option_checks_and_describes_itself():
    from torch_ao.options import Option, options_by_name

    tau = Option("tau", 0.25, "temperature of the soft sector masks", unit="sectors", minimum=0, open_minimum=True)
    assert tau.check(0.5) == 0.5
    with pytest.raises(ValueError, match="tau: expected a number > 0"):
        tau.check(0.0)
    assert tau.describe() == ("temperature of the soft sector masks. Unit: sectors. Range: (0, inf). "
                              "Default: 0.25.")
    fetch = Option("fetch", "nearest", "depth fetch", kind=str, choices=("nearest", "bilinear"))
    with pytest.raises(ValueError, match="fetch: expected one of"):
        fetch.check("cubic")
    steps = Option("steps", 3, "samples per side", kind=int, minimum=1)
    with pytest.raises(ValueError, match="steps: expected an integer >= 1"):
        steps.check(0)
    assert set(options_by_name((tau, fetch), (tau, steps))) == {"tau", "fetch", "steps"}
    with pytest.raises(ValueError, match="described twice"):
        options_by_name((tau,), (Option("tau", 1.0, "other"),))
