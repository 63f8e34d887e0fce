"""`--env.type=mujoco_teleop` as lerobot-eval steps it (issue 58): LeRobot's own vector env and reset options,
in this process. The commands themselves (lerobot-eval, lerobot-train's evaluation) run in test_lerobot_plugin.py.
"""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.e2e  # imports LeRobot (torch): seconds the quick suite should not pay


def test_one_scene_is_built_an_episode_and_the_autoreset_after_its_end_builds_none():
    """The vector env's autoreset at an episode's last step would build the next seed's scene only for lerobot-eval's
    rollout to build it again (its reset names the seed): LeRobot's FreezeAfterEpisodeEnd answers it with the
    terminal step instead, so an episode costs one scene build, as in `teleop eval`."""
    import teleop.lerobot_plugin  # noqa: F401 - registers --env.type=mujoco_teleop
    from lerobot.envs.configs import EnvConfig
    from lerobot.envs.utils import NEW_ROLLOUT_OPTION

    from teleop.lerobot_plugin.lerobot_env import make_lerobot_env

    steps = 4
    vec = EnvConfig.get_choice_class("mujoco_teleop")(episode_length=steps).create_envs(1)["mujoco_teleop"][0]
    fresh = make_lerobot_env("lift", "panda", fps=30, cameras=[], image_size=(96, 96), episode_length=steps, render_mode=None)
    try:
        session = vec.envs[0].unwrapped.session
        built: list[int] = []
        load = session.load
        session.load = lambda seed: (built.append(int(seed)), load(seed))[1]  # a spy: the real build runs

        first, _ = vec.reset(seed=[1000], options={NEW_ROLLOUT_OPTION: True})
        assert built == [1000]
        frame = vec.envs[0].render()  # the renderer was made with the env
        assert frame.shape == (96, 96, 3) and frame.dtype == np.uint8 and len(np.unique(frame.reshape(-1, 3), axis=0)) > 20

        action = np.asarray(first["agent_pos"], dtype=np.float32)  # hold the arm where it is
        for i in range(steps):
            obs, _, terminated, truncated, info = vec.step(action)
            assert bool(truncated[0]) == (i == steps - 1) and not terminated[0]
        assert "final_info" in info and "is_success" in info["final_info"]  # what lerobot-eval reads at the end
        assert built == [1000], "the autoreset after the episode's last step built a scene"
        assert vec.step(action)[0]["agent_pos"].tolist() == obs["agent_pos"].tolist()  # frozen: no physics either

        second, _ = vec.reset(seed=[1001], options={NEW_ROLLOUT_OPTION: True})
        assert built == [1000, 1001]
        expected, _ = fresh.reset(seed=1001)
        for key in ("agent_pos", "environment_state"):
            np.testing.assert_array_equal(second[key][0], expected[key])
        assert not np.array_equal(second["environment_state"][0], first["environment_state"][0])  # another seed's cube
    finally:
        vec.close()
        fresh.close()
