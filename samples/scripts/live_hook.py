"""Hook a live stream into an Engine: the sample character performs what a VMC sender sends.

    python samples/scripts/live_hook.py --out out/hook                  # listens on vmc://127.0.0.1:39539
    python samples/scripts/live_hook.py --out out/hook --send samples/motion/cmu_131_01.bvh

With --send the script streams the clip to the URL itself (no second terminal). The hook is
the three lines under "the hook": an Engine on a stage with a live binding (here the sample
scene's `suit`, given this URL), frames rendered as usual, each frame's report saying how the
binding is doing.
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from rigspace.runtime.engine import Engine, EngineSettings
from rigspace.sdk.color import linear_to_srgb

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "live.usda"


def streamer(url: str, bvh: str, stop: threading.Event) -> threading.Thread:
    """A thread that sends a BVH clip over VMC in real time, looping, until `stop` (what
    `rigspace live send` does)."""
    from rigspace.runtime.live.decoders.bvh import read_bvh
    from rigspace.runtime.live.send import humanoid_clip, send_vmc

    skeleton, motion, frame_time = read_bvh(bvh)
    rotations, roots = skeleton.pose(motion)
    clip = humanoid_clip(skeleton, rotations, roots, frame_time)
    return threading.Thread(target=send_vmc, args=(url, clip, 1.0, True, stop), daemon=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", default="vmc://127.0.0.1:39539", help="where the stream arrives")
    parser.add_argument("--send", metavar="BVH", help="also stream this clip to --url")
    parser.add_argument("--out", required=True, help="folder for the frames")
    parser.add_argument("--frames", type=int, default=30, help="frames to render (one a 1/10 s)")
    parser.add_argument("--size", default="320x180", help="WxH")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stop = threading.Event()
    sender = streamer(args.url, args.send, stop) if args.send else None
    # The hook: the engine opens the binding's source at the first frame, closes it at the end.
    with Engine(
        SCENE, EngineSettings(sources={"suit": args.url}, width=width, height=height)
    ) as engine:
        engine.open_live()  # listen before anything is sent
        if sender is not None:
            sender.start()
            time.sleep(0.1)
        for k in range(args.frames):
            frame = engine.render(float(k * 3))
            suit = frame.report.live[0]
            print(f"frame {k}: {suit['status']}, {suit['samples']} samples, "
                  f"{frame.report.characters[0]['decision']}")  # fmt: skip
            rgb = (linear_to_srgb(frame.beauty) * 255 + 0.5).astype(np.uint8)
            cv2.imwrite(str(out / f"hook_{k:03d}.png"), rgb[..., ::-1])
            time.sleep(0.1)
    stop.set()


if __name__ == "__main__":
    main()
