"""Fuzz every decoder with random and mutated bytes: `python -m rigspace.apps.live_fuzz`."""

from __future__ import annotations

import argparse
import resource
import sys
import time
import traceback
from collections.abc import Callable
from typing import Any

import numpy as np

from rigspace.runtime.live.decoders.bvh import BvhStreamDecoder, parse_bvh
from rigspace.runtime.live.decoders.evdev import EV_ABS, EV_KEY, EV_SYN, EVENT, EvdevDecoder
from rigspace.runtime.live.decoders.vmc import HUMAN_BODY_BONES, VmcDecoder, encode_frame
from rigspace.runtime.live.decoders.ximu3 import Ximu3Decoder

# A small hierarchy with mixed rotation orders and a 6-channel root, so the fuzzer needs no files.
FUZZ_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Spine
  {
    OFFSET 0 5 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 5 0
    }
  }
  JOINT LeftHip
  {
    OFFSET 1 -1 0
    CHANNELS 3 Zrotation Yrotation Xrotation
  }
}
"""


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _vmc_seed(rng: np.random.Generator) -> list[bytes]:
    bones = tuple(rng.choice(HUMAN_BODY_BONES, size=int(rng.integers(1, 56)), replace=False))
    q = _unit(rng, len(bones))
    return encode_frame(bones, q, rng.normal(size=3), None, float(rng.uniform(0, 1e4)))


def _bvh_seed(rng: np.random.Generator) -> list[bytes]:
    values = rng.uniform(-180, 180, size=12)
    line = " ".join(f"{v:.4f}" for v in values)
    prefix = "0 Avatar00 " if rng.random() < 0.3 else ""
    return [f"{prefix}{line}{' ||' if prefix else ''}\n".encode()]


def _ximu3_seed(rng: np.random.Generator) -> list[bytes]:
    w, x, y, z = _unit(rng, 1)[0]
    t = int(rng.integers(0, 2**40))
    lines = [f"Q,{t},{w:.6f},{x:.6f},{y:.6f},{z:.6f}\r\n".encode()]
    if rng.random() < 0.3:
        lines.append(f"I,{t},0.1,0.2,0.3,0.0,0.0,1.0\r\n".encode())
    return lines


def _evdev_seed(rng: np.random.Generator) -> list[bytes]:
    events = [
        EVENT.pack(1, int(rng.integers(0, 10**6)), EV_ABS, int(rng.integers(0, 6)), int(v))
        for v in rng.integers(-40000, 40000, size=int(rng.integers(1, 5)))
    ]
    if rng.random() < 0.3:
        events.append(EVENT.pack(1, 0, EV_KEY, 304, 1))
    events.append(EVENT.pack(1, 0, EV_SYN, 0, 0))
    return [b"".join(events)]


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One random mutation: bit flips, byte overwrites, truncation, insertion, or duplication."""
    if not data:
        return bytes(rng.integers(0, 256, size=int(rng.integers(1, 64)), dtype=np.uint8))
    buf = bytearray(data)
    kind = int(rng.integers(0, 6))
    if kind == 0:
        for i in rng.integers(0, len(buf), size=int(rng.integers(1, 8))):
            buf[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1:
        for i in rng.integers(0, len(buf), size=int(rng.integers(1, 8))):
            buf[i] = int(rng.integers(0, 256))
    elif kind == 2:
        buf = buf[: int(rng.integers(0, len(buf)))]
    elif kind == 3:
        at = int(rng.integers(0, len(buf) + 1))
        junk = rng.integers(0, 256, size=int(rng.integers(1, 32)), dtype=np.uint8).tobytes()
        buf[at:at] = junk
    elif kind == 4:
        buf += buf[: int(rng.integers(0, len(buf)))]
    else:
        for token in (b"nan", b"inf", b"-1e309", b"1e30", b"0"):
            at = int(rng.integers(0, len(buf)))
            buf[at : at + len(token)] = token
    return bytes(buf)


def _decoders() -> dict[str, tuple[Callable[[], Any], Callable, int]]:
    """Name -> (new decoder, seed generator, bound on its buffered state)."""
    skeleton = parse_bvh(FUZZ_BVH, "fuzz.bvh")[0]
    return {
        "vmc": (VmcDecoder, _vmc_seed, len(HUMAN_BODY_BONES) + 1),
        "bvh": (lambda: BvhStreamDecoder(skeleton), _bvh_seed, BvhStreamDecoder.MAX_LINE + 4096),
        "evdev": (EvdevDecoder, _evdev_seed, EVENT.size),
        "ximu3": (
            lambda: Ximu3Decoder(("pelvis", "thigh_l")),
            _ximu3_seed,
            2 * (Ximu3Decoder.MAX_LINE + 4096),
        ),
    }


def fuzz(name: str, nbytes: int, seed: int = 0) -> dict:
    """Feed decoder `name` at least `nbytes` of random and mutated input; returns its counts,
    the largest buffered state seen, and the failures (exceptions that escaped)."""
    make, seed_input, bound = _decoders()[name]
    decoder = make()
    rng = np.random.default_rng(seed)
    fed = 0
    largest = 0
    failures: list[str] = []
    start = time.perf_counter()
    while fed < nbytes:
        pick = rng.random()
        if pick < 0.25:
            chunks = [bytes(rng.integers(0, 256, size=int(rng.integers(1, 600)), dtype=np.uint8))]
        elif pick < 0.4:
            chunks = seed_input(rng)  # valid input keeps the decoder's state machine moving
        else:
            chunks = [mutate(c, rng) for c in seed_input(rng)]
        for chunk in chunks:
            fed += len(chunk)
            try:
                kw = {"channel": int(rng.integers(0, 2))} if name == "ximu3" else {}
                for frame in decoder.feed(chunk, time.monotonic(), **kw):
                    q = frame.rotations
                    if not (np.all(np.isfinite(q)) and np.allclose(np.linalg.norm(q, axis=1), 1)):
                        failures.append(f"non-unit rotation out of {chunk!r}")
            except Exception:
                failures.append(f"{chunk!r}\n{traceback.format_exc()}")
            largest = max(largest, decoder.buffered)
    if largest > bound:
        failures.append(f"buffered state grew to {largest} (bound {bound})")
    return {
        "decoder": name,
        "bytes": fed,
        "seconds": round(time.perf_counter() - start, 2),
        **decoder.counters.as_dict(),
        "max_buffered": largest,
        "failures": failures,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rigspace.apps.live_fuzz", description=__doc__)
    parser.add_argument("--bytes", type=int, default=1_000_000, help="bytes per decoder")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--decoder", choices=[*_decoders(), "all"], default="all")
    args = parser.parse_args(argv)
    names = list(_decoders()) if args.decoder == "all" else [args.decoder]
    failed = False
    for name in names:
        result = fuzz(name, args.bytes, args.seed)
        failures = result.pop("failures")
        print(" ".join(f"{k}={v}" for k, v in result.items()), f"failures={len(failures)}")
        for f in failures[:5]:
            print("  FAILURE:", f[:2000])
        failed |= bool(failures)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {peak:.0f} MiB")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
