"""What a suite that follows lerobot-eval's protocol declares (`libero-lerobot`,
`metaworld-lerobot`): LeRobot's env type, the size lerobot-eval renders, and the feature name
LeRobot gives each camera, so a published checkpoint's features map with no `lerobot_keys` and
the plan knows which image size to render (docs/lerobot.md, "lerobot-eval's protocol")."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LeRobotProtocol:
    env_type: str  # lerobot-eval's --env.type: "libero", "metaworld"
    image_size: int  # lerobot-eval's render size (its EnvConfig's, or the env class's own)
    features: tuple[tuple[str, str], ...]  # (Retain key, LeRobot's feature name)

    def feature(self, key: str) -> str | None:
        return dict(self.features).get(key)


class LeRobotProtocolSuite:
    """Mixin of a suite whose observations, episodes, limits and instructions are lerobot-eval's."""

    lerobot: LeRobotProtocol
