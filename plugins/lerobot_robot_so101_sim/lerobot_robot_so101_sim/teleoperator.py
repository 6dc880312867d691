"""so101-sim's scripted expert as a ``lerobot.teleoperators.Teleoperator``.

The expert plans from true object poses, which a real teleoperator never reads from its robot;
here it reads them from the sim robot connected in the same process (``connected_robot``), so
lerobot-record and lerobot-teleoperate run headless with no hardware and no person. lerobot
connects the teleoperator before the robot, so the robot is looked up at the first action.
"""

from __future__ import annotations

from typing import Any

from lerobot.teleoperators.teleoperator import Teleoperator
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

from lerobot_robot_so101_sim.config import TELEOP_TYPE, SO101SimExpertConfig
from lerobot_robot_so101_sim.registry import connected_robot
from so101_sim.utils.lerobot_cli import config_errors
from so101_sim.utils.units import FEATURE_NAMES


class SO101SimExpert(Teleoperator):
    """``--teleop.type=so101_sim_expert``: ``ScriptedExpert`` at the controls of the sim.

    Its actions are so101_leader's features. Each sim episode resets the expert with that
    episode's seed, as ``so101-sim record`` does, so the same seed gives the same demo; after
    an episode's end it asks the arm to stay where it is.
    """

    config_class = SO101SimExpertConfig
    name = TELEOP_TYPE

    def __init__(self, config: SO101SimExpertConfig) -> None:
        super().__init__(config)
        self.config = config
        self._connected = False
        self._expert: Any = None
        self._env: Any = None  # the env the expert was built for
        self._expert_episode: int | None = None
        self._last: tuple[tuple[int, int], dict[str, float]] | None = None

    @property
    def action_features(self) -> dict[str, type]:
        return dict.fromkeys(FEATURE_NAMES, float)

    @property
    def feedback_features(self) -> dict[str, type]:
        return {}

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def is_calibrated(self) -> bool:
        return True

    def connect(self, calibrate: bool = True) -> None:
        """Nothing to open; the sim robot may connect after this (lerobot-record's order)."""
        if self._connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        self._connected = True

    def calibrate(self) -> None:
        """Nothing to calibrate: the expert speaks LeRobot units."""

    def configure(self) -> None:
        """Nothing to configure."""

    def get_action(self) -> dict[str, float]:
        """The expert's next joint targets for the sim's current state (one per step: asked
        twice before the sim steps, it answers the same)."""
        if not self._connected:
            raise DeviceNotConnectedError(f"{self} is not connected; call connect() first")
        with config_errors(f"--teleop.type={TELEOP_TYPE}", (LookupError,)):  # one line
            robot = connected_robot(self.config.robot_id)
        index, seed, steps, over = robot.episode
        if over:
            return robot.held_action()
        if self._last is not None and self._last[0] == (index, steps):
            return dict(self._last[1])
        if self._expert is None or self._env is not robot.env:
            from so101_sim.expert import ScriptedExpert

            self._env = robot.env
            self._expert = ScriptedExpert(robot.env.task, model=robot.env.model,
                                          recover=self.config.recover)
            self._expert_episode = None
        if self._expert_episode != index:
            self._expert.reset(seed)
            self._expert_episode = index
        action = self._expert.select_action(robot.state_observation())
        out = dict(zip(FEATURE_NAMES, map(float, action), strict=True))
        self._last = ((index, steps), out)
        return dict(out)

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        """The expert takes no feedback."""

    def disconnect(self) -> None:
        if not self._connected:
            raise DeviceNotConnectedError(f"{self} is not connected; call connect() first")
        self._connected = False
        self._expert = self._env = self._last = None
