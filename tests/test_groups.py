"""The xdist groups of tests/conftest.py: the tests that share an expensive session fixture run on one worker, so that
the fixture is built once per run (a session fixture is built once per worker)."""

from __future__ import annotations

import pytest
from conftest import group_of

#: the session fixtures built once per run only if their users share a group (calibrated_trial is built once per
#: worker on purpose: its users are tests/test_trust.py's tests, one group each, on both workers)
SHARED = ("targetless_calibrated", "real_inspected", "urg_from_the_authors_nominal", "full_sweep_run")


def test_the_users_of_a_shared_run_are_one_group() -> None:
    together = [
        ["tests/test_real_walkthrough.py::test_inspect_proposes_a_rig_file[cardboard_box]",
         "tests/test_inspect_dh.py::test_real_urg_stand_proposes_alpha_90[room_240]",
         "tests/test_targetless.py::test_real_urg04lx_box_gives_one_verdict_for_all_or_half_of_its_scans"],
        ["tests/test_start_dependence.py::test_shipped_targetless_scenes_calibrate_with_the_starts_agreeing[room_box]",
         "tests/test_targetless.py::test_room_box_recovers_the_truth_within_4_sigma"],
        ["tests/test_cli_sim.py::test_run_closes_the_loop",
         "tests/test_output_names.py::test_no_command_leaves_a_temporary_name"],
    ]
    groups = [{group_of(n) for n in nodes} for nodes in together]
    assert all(len(g) == 1 for g in groups), groups
    assert len(set().union(*groups)) == len(together)  # three groups, not one
    # the others stay split as before: test_targetless's scenes and test_trust's cases one group each
    assert group_of("tests/test_targetless.py::test_random_dh_truths_in_the_room[11]") != group_of(
        "tests/test_targetless.py::test_random_dh_truths_in_the_room[12]")
    assert group_of("tests/test_inspect_dh.py::test_inspect_proposes_the_simulated_truth") == "test_inspect_dh"


def test_every_collected_user_of_a_shared_run_is_in_its_group(request: pytest.FixtureRequest) -> None:
    """Over the tests collected in this run (the whole suite under ``python -m pytest``): one group per shared
    fixture, whichever module uses it."""
    users: dict[str, set[str]] = {name: set() for name in SHARED}
    for item in request.session.items:
        for name in SHARED:
            if name in getattr(item, "fixturenames", ()):
                users[name].add(group_of(item.nodeid))
    assert all(len(groups) <= 1 for groups in users.values()), users
