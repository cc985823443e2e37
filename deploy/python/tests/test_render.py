"""``render_mode="rgb_array"``: the race as ``ctxrace race --render race.gif`` draws its
moments, as an ``(height, width, 3)`` uint8 array that follows the cars; bad modes raise."""

import gymnasium
import numpy as np
import pytest
from gymnasium.error import ClosedEnvironmentError, ResetNeeded
from gymnasium.utils.env_checker import check_env

import ctxrace

TRACK = "generated:0"

#: The ego's colour in the picture.
EGO_RED = (220, 30, 30)


def ego_centre(picture):
    """The mean (row, column) of the ego's red pixels above the legend band, and their count."""
    rows, cols = np.nonzero((picture[:-40] == EGO_RED).all(axis=2))
    return np.array([rows.mean(), cols.mean()]), len(rows)


def test_frames_are_rgb_arrays_of_the_race_that_follow_the_cars():
    env = gymnasium.make("ctxrace/Race-v0", track=TRACK, rivals=2, render_mode="rgb_array")
    assert env.metadata["render_modes"] == ["rgb_array"]
    # the default scenario decides every 0.1 s
    assert env.metadata["render_fps"] == pytest.approx(10.0)
    env.reset(seed=3, options={"context": (0.0, 0.0)})
    start = env.render()
    assert start.dtype == np.uint8 and start.ndim == 3
    assert start.shape[1:] == (1000, 3) and 200 < start.shape[0] < 2000
    # white background, black walls, the ego's red
    assert (start == 255).all(axis=2).mean() > 0.5
    assert (start == 0).all(axis=2).any()
    at_start, n = ego_centre(start)
    assert n > 20
    for _ in range(6):
        _, _, terminated, truncated, _ = env.step(np.array([0.0, 0.0], dtype=np.float32))
        assert not (terminated or truncated)
    later = env.render()
    assert later.shape == start.shape
    moved, _ = ego_centre(later)
    # 0.6 s at up to 3 m/s: the car and its ring move several pixels along the track
    assert np.linalg.norm(moved - at_start) > 5, (at_start, moved)
    # a new episode starts a new picture
    env.reset(seed=3, options={"context": (0.0, 0.0)})
    np.testing.assert_array_equal(env.render(), start)


def test_render_fps_follows_the_decision_period():
    env = ctxrace.RaceEnv(TRACK, render_mode="rgb_array", physics_steps_per_action=5)
    assert env.metadata["render_fps"] == pytest.approx(20.0)
    assert ctxrace.RaceEnv.metadata["render_fps"] == pytest.approx(10.0)


def test_check_env_passes_with_rgb_array_rendering():
    env = gymnasium.make("ctxrace/Race-v0", track=TRACK, rivals=1, render_mode="rgb_array")
    check_env(env.unwrapped)
    env.reset(seed=0)
    assert env.render().shape[2] == 3


def test_bad_modes_and_renders_out_of_turn_raise():
    with pytest.raises(ValueError, match="'rgb_array'.*or nothing"):
        ctxrace.RaceEnv(TRACK, render_mode="human")
    env = ctxrace.RaceEnv(TRACK, render_mode="rgb_array")
    with pytest.raises(ResetNeeded, match="call reset"):
        env.render()
    assert ctxrace.RaceEnv(TRACK).render() is None
    env.reset(seed=0)
    env.close()
    with pytest.raises(ClosedEnvironmentError):
        env.render()


def test_a_vector_draws_every_env_and_an_autoreset_env_starts_a_new_picture():
    env = ctxrace.make_vec(TRACK, 2, seed=0, render_mode="rgb_array")
    assert env.metadata["render_modes"] == ["rgb_array"]
    assert env.metadata["render_fps"] == pytest.approx(10.0)
    env.reset(options={"context": np.zeros((2, 2))})
    first = env.render()
    assert isinstance(first, tuple) and len(first) == 2
    # env 0 turns full left into the wall, env 1 drives on
    actions = np.array([[-1.0, 1.0], [0.0, -0.5]])
    ended = False
    while not ended:
        _, _, terminated, truncated, _ = env.step(actions)
        ended = terminated[0] or truncated[0]
        assert not (terminated[1] or truncated[1])
    crashed, _ = env.render()
    assert not np.array_equal(crashed, first[0])
    env.step(actions)  # env 0 resets: its picture starts again
    restarted, driving = env.render()
    np.testing.assert_array_equal(restarted, first[0])
    assert not np.array_equal(driving, first[1])
    with pytest.raises(ValueError, match="'rgb_array'"):
        ctxrace.make_vec(TRACK, 1, render_mode="human")
    assert ctxrace.make_vec(TRACK, 1).render() is None
