"""`python -m rigspace.apps.capsules SCENE CHARACTER BUNDLE`: fit shadow capsules on a scene's
character and add them to a model bundle made before capsules existed (rigspace.sdk.capsules)."""

from __future__ import annotations

import argparse
import sys

from rigspace.sdk.capsules import CapsuleError, add_to_bundle, fit_capsules
from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.posing import CharacterRig
from rigspace.sdk.stage import open_stage


def main(argv: list[str] | None = None) -> int:
    """`python -m rigspace.apps.capsules SCENE CHARACTER BUNDLE`: fit and add to a bundle."""
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.capsules", description=main.__doc__
    )
    parser.add_argument("scene", help="the stage holding the character")
    parser.add_argument("character", help="the neural character prim's path, e.g. /World/Hero")
    parser.add_argument("bundle", help="the model bundle folder to add capsules.json to")
    args = parser.parse_args(argv)
    try:
        stage = open_stage(args.scene)
        prim = stage.GetPrimAtPath(args.character)
        if not prim:
            raise CapsuleError(
                f"{args.scene} has no prim {args.character}.", "pass the character's prim path."
            )
        capsules = fit_capsules(CharacterRig(prim))
        path = add_to_bundle(capsules, args.bundle)
    except RigspaceError as exc:
        print(f"rigspace capsules: error: {exc}", file=sys.stderr)
        return 1
    print(f"{len(capsules)} capsules -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
