"""A VMC sender in a process of its own, for the `rigspace live` tests: the CMU clip on
HumanBodyBones (optionally turned: poses the clip never has), in real time, looping, until
SIGTERM. Its own process, so a renderer holding this process's GIL cannot starve it.

python -m tests.runtime.live.vmc_sender vmc://127.0.0.1:PORT [--turn DEGREES]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from rigspace.runtime.live.decoders.bvh import read_bvh
from rigspace.runtime.live.send import HumanoidClip, humanoid_clip, send_vmc
from rigspace.sdk.rotations import quat_multiply
from tests.runtime.live.conftest import CMU_CLIP


def cmu_clip(turn: float = 0.0) -> HumanoidClip:
    """The CMU clip as `live send` streams it, its hips turned `turn` degrees about the vertical
    (0: the clip itself)."""
    skeleton, motion, frame_time = read_bvh(CMU_CLIP)
    clip = humanoid_clip(skeleton, *skeleton.pose(motion), frame_time)
    if not turn:
        return clip
    h = np.radians(turn) / 2
    rotations = clip.rotations.copy()
    hips = list(clip.bones).index("Hips")
    rotations[:, hips] = quat_multiply(
        np.array([np.cos(h), 0.0, np.sin(h), 0.0]), rotations[:, hips]
    )
    return dataclasses.replace(clip, rotations=rotations)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("url")
    parser.add_argument("--turn", type=float, default=0.0)
    args = parser.parse_args()
    # SIGTERM's default action ends it: a handler setting a threading.Event could deadlock on
    # the lock the interrupted Event.wait holds (seen once: close() waited out its 30 s).
    send_vmc(args.url, cmu_clip(args.turn), 1.0, True)


if __name__ == "__main__":
    main()
