"""``trajectory_groups`` in the config: the default group of every limited joint, the checks of a
group's joints (known, limited, one bus, one group each), and a config that comes back unchanged."""

from __future__ import annotations

from typing import Any

import pytest

from can_config import ConfigError, config_to_dict, parse_config

BUSES = [{"name": "can0", "interface": "socketcand", "channel": "can0"},
         {"name": "can1", "interface": "socketcand", "channel": "can1"}]
ARM = {"joint": "limited", "min_deg": -90, "max_deg": 90}


def config(groups: Any = None, **more: Any) -> dict[str, Any]:
    drives = [{"name": "wheel", "node_id": 1}, {"name": "shoulder", "node_id": 2, **ARM},
              {"name": "elbow", "node_id": 3, **ARM}, {"name": "wrist", "node_id": 1, "bus": "can1", **ARM}]
    out: dict[str, Any] = {"buses": BUSES, "drives": drives, **more}
    if groups is not None:
        out["trajectory_groups"] = groups
    return out


def test_without_the_key_every_limited_joint_is_the_arm_controller() -> None:
    text = config()
    text["drives"] = text["drives"][:3]
    (group,) = parse_config(text).trajectory_groups
    assert group.name == "arm_controller" and group.joints == ("shoulder", "elbow")
    assert group.goal_tolerance_deg == 0.2 and group.goal_time_tolerance_s == 1.0
    no_arm = {"buses": BUSES, "drives": [{"name": "wheel", "node_id": 1}]}
    assert parse_config(no_arm).trajectory_groups == ()
    assert parse_config(config([])).trajectory_groups == ()


def test_groups_as_given_come_back_unchanged() -> None:
    parsed = parse_config(config([{"name": "arm", "joints": ["shoulder", "elbow"], "goal_time_tolerance_ms": 250},
                                  {"name": "hand", "joints": ["wrist"], "path_tolerance_deg": 0}]))
    assert [(g.name, g.joints, g.goal_time_tolerance_s) for g in parsed.trajectory_groups] == \
        [("arm", ("shoulder", "elbow"), 0.25), ("hand", ("wrist",), 1.0)]
    assert parse_config(config_to_dict(parsed)) == parsed


@pytest.mark.parametrize(("groups", "error"), [
    ([{"name": "arm", "joints": ["shoulder", "knee"]}], r"trajectory_groups\[0\]\.joints: names drive 'knee'"),
    ([{"name": "arm", "joints": ["shoulder", "wheel"]}], r"'wheel' is a continuous joint"),
    ([{"name": "arm", "joints": ["shoulder", "wrist"]}], r"on buses \['can0', 'can1'\]; a group follows one bus"),
    ([{"name": "a", "joints": ["shoulder"]}, {"name": "b", "joints": ["shoulder"]}], r"'shoulder' is in group 'a'"),
    ([{"name": "a", "joints": ["shoulder"]}, {"name": "a", "joints": ["elbow"]}], r"'a' is used twice"),
    ([{"name": "arm", "joints": []}], r"expected a non-empty list of drive names"),
    ([{"name": "arm", "joints": ["elbow"], "stop_deceleration_deg_s2": 0}], r"stop_deceleration_deg_s2: got 0"),
    ({"name": "arm"}, r"trajectory_groups: got .*expected a list of groups"),
])
def test_a_bad_group_says_what_is_wrong(groups: Any, error: str) -> None:
    with pytest.raises(ConfigError, match=error):
        parse_config(config(groups))
