"""Which env camera feeds each camera input of a policy (``so101-sim eval --camera-map``).

A policy trained on a real SO-101 names its cameras after that rig (``front`` and ``wrist``,
or ``top``, ``laptop``, ``phone``); the env renders ``front``, ``side`` and ``wrist`` (on the
gripper). A map such as ``top=front,laptop=side`` feeds the env's front camera to the
policy's ``top`` input. Policy cameras already named like an env camera map to it unless the
map says otherwise.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from so101_sim.tasks import ALL_CAMERAS as CAMERAS


def parse_camera_map(text: str) -> dict[str, str]:
    """ "top=front,wrist=side" -> {"top": "front", "wrist": "side"} (policy name -> env camera)."""
    out: dict[str, str] = {}
    for item in (p.strip() for p in text.split(",") if p.strip()):
        policy_cam, sep, env_cam = (s.strip() for s in item.partition("="))
        if not sep or not policy_cam or not env_cam:
            raise ValueError(f"camera map entry {item!r} is invalid; expected "
                             f"POLICY_CAMERA=ENV_CAMERA, e.g. top=front (env cameras: "
                             f"{', '.join(CAMERAS)})")
        if policy_cam in out:
            raise ValueError(f"camera map names policy camera {policy_cam!r} twice; give each "
                             "policy camera one env camera")
        out[policy_cam] = env_cam
    if not out:
        raise ValueError(f"camera map {text!r} is empty; expected e.g. top=front,wrist=side")
    return out


def resolve_camera_map(policy_cameras: Iterable[str], camera_map: dict[str, str] | None,
                       where: str, log: Callable[[str], None] = print) -> dict[str, str]:
    """Every camera of the policy -> the env camera that feeds it; errors name the fix. One
    env camera feeding several policy cameras is allowed (a one-camera rig), with a note."""
    cams = list(policy_cameras)
    asked = dict(camera_map or {})
    unknown = sorted(set(asked) - set(cams))
    if unknown:
        raise ValueError(f"--camera-map names {unknown}, which {where} does not have; its "
                         f"cameras are {cams or 'none'}")
    bad = sorted({v for v in asked.values() if v not in CAMERAS})
    if bad:
        raise ValueError(f"--camera-map maps onto {bad}; the env renders {list(CAMERAS)}")
    out = {}
    for cam in cams:
        env_cam = asked.get(cam, cam)
        if env_cam not in CAMERAS:
            raise ValueError(f"{where} expects camera {cam!r} (observation.images.{cam}); the "
                             f"env renders {list(CAMERAS)}: map it with --camera-map "
                             f"{cam}={CAMERAS[0]} (or {cam}={CAMERAS[-1]}), or rename the "
                             "feature")
        out[cam] = env_cam
    for env_cam, policy_cams in shared_cameras(out).items():
        log(f"so101-sim eval: note: --camera-map feeds env camera {env_cam} to policy cameras "
            f"{' and '.join(policy_cams)} (the same image in each): fine for a one-camera "
            "rig; otherwise map each policy camera to its own env camera")
    return out


def shared_cameras(mapping: dict[str, str]) -> dict[str, list[str]]:
    """Env cameras that feed more than one policy camera -> those policy cameras."""
    fed: dict[str, list[str]] = {}
    for p, e in mapping.items():
        fed.setdefault(e, []).append(p)
    return {e: ps for e, ps in fed.items() if len(ps) > 1}


def shown_camera_map(mapping: dict[str, str]) -> dict[str, str]:
    """The entries a summary states: renamed cameras, and every camera of a shared one."""
    shared = shared_cameras(mapping)
    return {p: e for p, e in mapping.items() if p != e or e in shared}


def describe_camera_map(mapping: dict[str, str]) -> str:
    """ "policy top <- env front, policy wrist <- env side" for the renamed cameras, and for
    every policy camera of an env camera that feeds several."""
    return ", ".join(f"policy {p} <- env {e}" for p, e in shown_camera_map(mapping).items())
