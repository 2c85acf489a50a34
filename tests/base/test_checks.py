"""The one-value checks every config uses (d2gs_np/base/checks.py): what each accepts, what it
refuses and how the refusal reads (the name, the range, the hint and the value)."""
import math

import numpy as np
import pytest

from d2gs_np.base.checks import check_bool, check_choice, check_int, check_number, name_items


@pytest.mark.parametrize("value", [0, 1, 0.5, np.float32(0.25), np.float64(1.0), np.int64(1), np.int8(0)])
def test_a_number_in_range_is_returned_as_a_float(value):
    out = check_number(value, "C.x", 0.0, 1.0)
    assert type(out) is float and out == float(value)


@pytest.mark.parametrize("value", [True, False, np.bool_(True), "0.5", None, [0.5], 1j, math.nan, math.inf, -math.inf,
                                   np.float64("nan"), 10 ** 400])
def test_a_number_refuses_bools_strings_non_finite_and_ints_too_large_for_a_float(value):
    with pytest.raises(ValueError, match=r"^C\.x must be a finite number; got "):
        check_number(value, "C.x")


def test_a_number_s_bounds_are_closed_unless_open():
    assert check_number(0.0, "C.x", 0.0, 1.0) == 0.0 and check_number(1.0, "C.x", 0.0, 1.0) == 1.0
    with pytest.raises(ValueError, match=r"C\.x must be a finite number in \(0, 1\]; got 0\.0"):
        check_number(0.0, "C.x", 0.0, 1.0, lo_open=True)
    with pytest.raises(ValueError, match=r"C\.x must be a finite number in \[0, 1\); got 1"):
        check_number(1, "C.x", 0.0, 1.0, hi_open=True)
    assert check_number(np.nextafter(1.0, 0.0), "C.x", 0.0, 1.0, hi_open=True) < 1.0


def test_a_number_s_refusal_reads_one_sided_ranges_and_the_hint():
    with pytest.raises(ValueError, match=r"^L\.w must be a finite number >= 0 \(0 = term off\); got -1$"):
        check_number(-1, "L.w", 0.0, hint="0 = term off")
    with pytest.raises(ValueError, match=r"^L\.e must be a finite number > 0; got 0\.0$"):
        check_number(0.0, "L.e", 0.0, lo_open=True)
    with pytest.raises(ValueError, match=r"^L\.c must be a finite number < 1\.41421; got 2$"):
        check_number(2, "L.c", hi=2 ** 0.5, hi_open=True)
    with pytest.raises(ValueError, match=r"^T\.b must be a finite number in \[0, 1\] \(an RGB colour\); got 2$"):
        check_number(2, "T.b", 0.0, 1.0, hint="an RGB colour")


@pytest.mark.parametrize("value", [0, 1, 7, np.int64(3), np.uint8(255), 10 ** 30])
def test_an_integer_in_range_is_returned_as_an_int(value):
    out = check_int(value, "C.n", 0)
    assert type(out) is int and out == int(value)


@pytest.mark.parametrize("value", [True, False, np.bool_(False), 2.0, np.float64(3.0), "3", None, math.nan])
def test_an_integer_refuses_bools_floats_and_strings(value):
    with pytest.raises(ValueError, match=r"^C\.n must be an integer; got "):
        check_int(value, "C.n")


def test_an_integer_s_bounds_are_inclusive_and_read_exactly():
    assert check_int(1, "C.n", 1, 3) == 1 and check_int(3, "C.n", 1, 3) == 3
    with pytest.raises(ValueError, match=r"^TrainConfig\.iters must be an integer >= 1; got 0$"):
        check_int(0, "TrainConfig.iters", 1)
    with pytest.raises(ValueError, match=r"^C\.n must be an integer in \[1, 3\]; got 4$"):
        check_int(4, "C.n", 1, 3)
    with pytest.raises(ValueError, match=r"^C\.n must be an integer <= 3 \(frames\); got 4$"):
        check_int(4, "C.n", hi=3, hint="frames")
    big = 10 ** 30  # bounds are compared as ints (no float rounding) and printed in full
    assert check_int(big, "C.n", big) == big
    with pytest.raises(ValueError, match=r"^C\.n must be an integer >= 1000000000000000000000000000000; got 999"):
        check_int(big - 1, "C.n", big)


@pytest.mark.parametrize("value", [True, False, np.bool_(True), np.bool_(False)])
def test_a_flag_is_true_or_false(value):
    out = check_bool(value, "C.f")
    assert type(out) is bool and out == bool(value)


@pytest.mark.parametrize("value", [0, 1, 1.0, "true", "yes", None, np.int64(1)])
def test_a_flag_refuses_numbers_and_strings(value):
    with pytest.raises(ValueError, match=r"^D\.absgrad must be true or false; got "):
        check_bool(value, "D.absgrad")


def test_a_choice_is_one_of_the_strings():
    assert check_choice("on", "T.blur", ("auto", "on", "off")) == "on"
    for bad in ("ON", "", None, 1, ("auto",), True):
        with pytest.raises(ValueError, match=r"^T\.blur must be one of \('auto', 'on', 'off'\); got "):
            check_choice(bad, "T.blur", ("auto", "on", "off"))
    with pytest.raises(ValueError, match=r"must be one of \('a', 'b'\) \(the hint\); got 'c'$"):
        check_choice("c", "X.k", ["a", "b"], hint="the hint")


def test_name_items_names_at_most_the_limit():
    assert name_items(["a"]) == "a"
    assert name_items(["a", "b", "c"]) == "a, b and c"
    assert name_items("abcdef", limit=2) == "a, b and 4 more"


def test_check_scalar_takes_0d_arrays_and_refuses_other_shapes_and_non_numbers():
    from d2gs_np.base.checks import check_scalar

    assert check_scalar(np.array(0.25), "t") == 0.25 and type(check_scalar(np.float32(2), "t")) is float
    with pytest.raises(ValueError, match=r"t must be a scalar; got an array of shape \(2,\)"):
        check_scalar(np.zeros(2), "t")
    for bad in (True, "1", None, np.array(np.nan), float("inf")):
        with pytest.raises(ValueError, match="t must be a finite number >= 0"):
            check_scalar(bad, "t", 0.0)
    with pytest.raises(ValueError, match="tau must be a finite number >= 0"):
        check_scalar(-1e-300, "tau", 0.0)
