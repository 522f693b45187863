"""What UsdSkel binds to a skeleton: its animation (inherited down namespace) and skinned meshes.

Every rigspace look-up of a skeleton's animation or meshes goes through here, so that
inspect, validation, capture and the runtime agree with UsdSkel itself. UsdSkel resolves
`skel:animationSource` like `skel:skeleton`: the nearest opinion on the Skeleton or an
ancestor (typically the SkelRoot, as exporters write it) that has SkelBindingAPI applied,
answered by `UsdSkel.Cache` populated from the SkelRoot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pxr import Usd, UsdGeom, UsdSkel

ANIMATION_SOURCE = "skel:animationSource"


@dataclass
class SkelBinding:
    """A Skeleton with what UsdSkel binds to it under its SkelRoot."""

    skeleton: UsdSkel.Skeleton
    root: UsdSkel.Root | None
    cache: UsdSkel.Cache
    animation: Usd.Prim | None
    """The bound SkelAnimation, own or inherited (None: the skeleton holds its rest pose)."""
    skinning: list[UsdSkel.SkinningQuery] = field(default_factory=list)
    """Visible Meshes under the SkelRoot skinned by this skeleton (with joint influences)."""

    @property
    def query(self) -> UsdSkel.SkeletonQuery:
        return self.cache.GetSkelQuery(self.skeleton)


def skel_binding(skeleton: Usd.Prim) -> SkelBinding:
    """The skeleton's animation and skinned meshes as UsdSkel resolves them."""
    skel = UsdSkel.Skeleton(skeleton)
    cache = UsdSkel.Cache()
    root = UsdSkel.Root.Find(skeleton)
    if root:
        cache.Populate(root, Usd.TraverseInstanceProxies())
    binding = SkelBinding(skel, root if root else None, cache, _animation(skel, cache))
    if root:
        for found in cache.ComputeSkelBindings(root, Usd.TraverseInstanceProxies()):
            if found.GetSkeleton().GetPrim() != skeleton:
                continue
            for query in found.GetSkinningTargets():
                prim = query.GetPrim()
                if not prim.IsA(UsdGeom.Mesh) or not query.HasJointInfluences():
                    continue
                if UsdGeom.Imageable(prim).ComputeVisibility() == UsdGeom.Tokens.invisible:
                    continue
                binding.skinning.append(query)
    return binding


def _animation(skel: UsdSkel.Skeleton, cache: UsdSkel.Cache) -> Usd.Prim | None:
    query = cache.GetSkelQuery(skel)
    anim = query.GetAnimQuery() if query else None
    if anim:
        return anim.GetPrim()
    # Outside a SkelRoot UsdSkel poses nothing, but the binding still reads the same way.
    source = UsdSkel.BindingAPI(skel.GetPrim()).GetInheritedAnimationSource()
    return source if source and source.IsA(UsdSkel.Animation) else None


def bound_animation(skeleton: Usd.Prim) -> Usd.Prim | None:
    """The SkelAnimation bound to `skeleton`: its own skel:animationSource or an ancestor's."""
    return _animation(UsdSkel.Skeleton(skeleton), _populated(skeleton))


def _populated(skeleton: Usd.Prim) -> UsdSkel.Cache:
    cache = UsdSkel.Cache()
    root = UsdSkel.Root.Find(skeleton)
    if root:
        cache.Populate(root, Usd.TraverseInstanceProxies())
    return cache


def ignored_animation_sources(skeleton: Usd.Prim) -> list[str]:
    """Prims at or above `skeleton` that author skel:animationSource without SkelBindingAPI.

    UsdSkel ignores those opinions (the API schema must be applied for its properties to
    count); naming them turns "no animation" into a fix.
    """
    ignored = []
    prim = skeleton
    while prim and not prim.IsPseudoRoot():
        rel = prim.GetRelationship(ANIMATION_SOURCE)
        if rel and rel.HasAuthoredTargets() and not prim.HasAPI(UsdSkel.BindingAPI):
            ignored.append(str(prim.GetPath()))
        prim = prim.GetParent()
    return ignored
