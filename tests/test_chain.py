"""calib.chain: the loop P X C = Y solved for each member, both setups, and the motions."""

from __future__ import annotations

import numpy as np
import pytest

from calib import chain
from calib.geometry import invert
from tests.support.helpers import exact_stations


@pytest.fixture(params=["eye_in_hand", "eye_to_hand"])
def stations(request):
    return exact_stations(request.param, 6, seed=4)


def test_every_member_of_the_loop_is_recovered(stations):
    cell, P, C = stations
    X, Y, setup = cell.hand_eye, cell.target_pose, cell.setup
    assert np.allclose(chain.camera_from_robot(P, X, Y, setup), C, atol=1e-12)
    assert np.allclose(chain.robot_from_camera(C, X, Y, setup), P, atol=1e-12)
    assert np.allclose(chain.target_from_station(P, X, C, setup), Y, atol=1e-12)
    assert np.allclose(chain.hand_eye_from_station(P, Y, C, setup), X, atol=1e-12)
    # the loop written in the frames of docs/conventions.md
    if setup == "eye_in_hand":  # T_base_tcp T_tcp_cam T_cam_target = T_base_target
        assert np.allclose(P @ X @ C, Y, atol=1e-12)
    else:  # inv(T_base_tcp) T_base_cam T_cam_target = T_tcp_target
        assert np.allclose(invert(P) @ X @ C, Y, atol=1e-12)


def test_robot_chain_is_its_own_inverse(stations):
    cell, P, _ = stations
    twice = chain.robot_chain(chain.robot_chain(P, cell.setup), cell.setup)
    assert np.allclose(twice, P, atol=1e-12)
    assert (chain.robot_chain(P, cell.setup) is P) == (cell.setup == "eye_in_hand")


def test_motions_satisfy_ax_equals_xb(stations):
    cell, P, C = stations
    m = chain.station_motions(chain.robot_chain(P, cell.setup), C)
    assert len(m.A) + m.skipped == 15 and m.pairs.shape == (len(m.A), 2)
    assert np.allclose(m.A @ cell.hand_eye, cell.hand_eye @ m.B, atol=1e-12)


def test_unknown_setup_is_named():
    with pytest.raises(ValueError, match="unknown setup 'hand_eye'"):
        chain.check_setup("hand_eye")
    with pytest.raises(ValueError, match="choose eye_in_hand or eye_to_hand"):
        chain.robot_chain(np.eye(4), "eye-in-hand")
