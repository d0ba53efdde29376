"""The one check of a named choice that every configuration makes."""

import pytest

from dronefl.validation import check_one_of


def test_a_choice_outside_the_set_is_named_with_the_option_and_every_choice():
    check_one_of("rest", ("next", "rest"), "--planner-distance")  # passes
    check_one_of("ours", {"ours": 1, "paper": 2}, "--config")  # a registry's keys
    with pytest.raises(ValueError) as error:
        check_one_of("later", ("next", "rest"), "--planner-distance")
    assert str(error.value) == "--planner-distance: 'later' is not one of next, rest"
    with pytest.raises(ValueError, match="--config: 'nope' is not one of ours, paper"):
        check_one_of("nope", {"ours": 1, "paper": 2}, "--config")
