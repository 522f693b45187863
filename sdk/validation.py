"""Scene validation: USD's own validators plus rigspace's, run through UsdValidation.

A rigspace validator is a `ValidatorSpec` (plugin kind "validator", entry-point group
`rigspace.validators`): a function from a prim to `Issue`s. Each is registered in USD's
`UsdValidation.ValidationRegistry` as `rigspace:<name>` and runs in the same
`ValidationContext` as USD's built-in validators, so every finding has the same shape:
severity, validator, prim and a message that names the fix. Rules report, never raise.

The built-in rules live in sdk/character_rules.py (stage, characters, models, textures)
and sdk/ring_rules.py (capture ring, live bindings); what a rule is, in sdk/issues.py.
They are the one set of checks: `rigspace inspect` reports them all, and
`require_valid` makes capture and render refuse the errors of the rules that concern
them, in the same words (docs/conventions.md, "Validation").
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from pxr import Sdf, Tf, Usd, UsdValidation

from rigspace.sdk import schema
from rigspace.sdk.cache_rules import CONTROLS, POINT_CACHE
from rigspace.sdk.character_rules import (
    CHARACTER_MODEL,
    CHARACTER_SKELETON,
    STAGE_METADATA,
    TEXTURES,
    animation_time_range,
    character_animation,
    character_skeleton,
    resolve_character,
    unreadable_layer_issues,
)
from rigspace.sdk.errors import RigspaceError, SceneError
from rigspace.sdk.issues import (
    CAPTURE,
    ERROR,
    PURPOSES,
    RENDER,
    WARNING,
    Issue,
    ValidatorSpec,
    error,
    warning,
)
from rigspace.sdk.plugins import Kind, discover
from rigspace.sdk.ring_rules import (
    CAPTURE_RING,
    LIVE_BINDING,
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    url_problem,
)

__all__ = [
    "BUILTIN",
    "CAPTURE",
    "CAPTURE_RING",
    "CHARACTER_MODEL",
    "CHARACTER_SKELETON",
    "CONTROLS",
    "ERROR",
    "LIVE_BINDING",
    "MAX_RESOLUTION",
    "MIN_RESOLUTION",
    "POINT_CACHE",
    "PURPOSES",
    "RENDER",
    "STAGE_METADATA",
    "TEXTURES",
    "VALIDATORS",
    "WARNING",
    "Finding",
    "Issue",
    "ValidatorSpec",
    "animation_time_range",
    "character_animation",
    "character_skeleton",
    "error",
    "require_readable",
    "require_valid",
    "resolve_character",
    "rules",
    "url_problem",
    "validate",
    "warning",
]
PREFIX = "rigspace:"

VALIDATORS: Kind[ValidatorSpec] = Kind("validator", "rigspace.validators", ValidatorSpec)


@dataclass(frozen=True)
class Finding:
    """A validation result from any validator, USD's or ours."""

    severity: str
    validator: str
    code: str
    prim: str
    message: str
    blocks: tuple[str, ...] = ()
    """The commands that refuse the scene for it (an error of a rigspace rule); USD's own
    validators report compliance and stop none."""

    def as_dict(self) -> dict[str, object]:
        return {
            "severity": self.severity,
            "validator": self.validator,
            "code": self.code,
            "prim": self.prim,
            "message": self.message,
            "blocks": list(self.blocks),
        }


BUILTIN = (
    STAGE_METADATA,
    CHARACTER_SKELETON,
    CHARACTER_MODEL,
    CAPTURE_RING,
    LIVE_BINDING,
    TEXTURES,
    POINT_CACHE,
    CONTROLS,
)
"""Always run; the entry-point group adds plugins' rules (the built-ins are declared there
too, for discovery's sake, and are not run twice)."""


def rules() -> tuple[list[ValidatorSpec], dict[str, str]]:
    """The built-in rules and the installed plugins' rules; plugin name -> why it failed."""
    plugins = discover(VALIDATORS)
    failed = dict(plugins.failed)
    names = {spec.name for spec in BUILTIN}
    extra = []
    for plugin_name, spec in plugins.specs.items():
        if spec in BUILTIN:
            continue
        if spec.name in names:
            failed[plugin_name] = f"its rule name {spec.name!r} is a built-in rule's"
            continue
        extra.append(spec)
    return [*BUILTIN, *extra], failed


# ---------------------------------------------------------------------------------------
# Registration with UsdValidation and running


_SEVERITY = {ERROR: UsdValidation.ValidationErrorType.Error}
_registered: dict[str, UsdValidation.Validator] = {}
_failures: list[BaseException] = []
_blocks: dict[tuple[str, str, str], tuple[str, ...]] = {}
"""(code, prim, message) -> the commands an error stops, noted while USD runs the rules."""


def _blocked(spec: ValidatorSpec, issue: Issue) -> tuple[str, ...]:
    """The commands that refuse the scene for `issue` (none for a warning)."""
    if issue.severity != ERROR:
        return ()
    return tuple(p for p in spec.purposes if issue.purposes is None or p in issue.purposes)


def _usd_task(spec: ValidatorSpec):
    def task(subject, *_time_range):
        try:
            stage = subject if spec.stage else subject.GetStage()
            prim = stage.GetPseudoRoot() if spec.stage else subject
            found = []
            for issue in spec.check(prim):
                _blocks[(issue.code, str(prim.GetPath()), issue.message)] = _blocked(spec, issue)
                found.append(
                    UsdValidation.ValidationError(
                        issue.code,
                        _SEVERITY.get(issue.severity, UsdValidation.ValidationErrorType.Warn),
                        [UsdValidation.ValidationErrorSite(stage, prim.GetPath())],
                        issue.message,
                    )
                )
            return found
        except Exception as exc:  # a bug in a rule: re-raised after validation (loudly)
            _failures.append(exc)
            return []

    return task


def register(specs: Iterable[ValidatorSpec]) -> list[UsdValidation.Validator]:
    """Register rules with USD's validation registry (once per name per process)."""
    registry = UsdValidation.ValidationRegistry()
    validators = []
    for spec in specs:
        name = PREFIX + spec.name
        if name not in _registered:
            if not registry.HasValidator(name):
                metadata = UsdValidation.ValidatorMetadata(
                    name=name, keywords=["rigspace"], doc=spec.doc, isSuite=False
                )
                if spec.stage:
                    registry.RegisterStageValidator(metadata, _usd_task(spec))
                else:
                    registry.RegisterPrimValidator(metadata, _usd_task(spec))
            _registered[name] = registry.GetOrLoadValidatorByName(name)
        validators.append(_registered[name])
    return validators


def _site_path(err: UsdValidation.ValidationError) -> str:
    """The prim or property a finding is about, else its layer ("" for the stage itself)."""
    for site in err.GetSites():
        if site.IsProperty() and site.GetProperty():
            return str(site.GetProperty().GetPath())
        if site.IsPrim() and site.GetPrim():
            path = site.GetPrim().GetPath()
            return "" if path == Sdf.Path.absoluteRootPath else str(path)
        if site.GetLayer():
            return site.GetLayer().identifier
    return ""


def validate(stage: Usd.Stage, include_usd: bool = True) -> list[Finding]:
    """Run USD's built-in validators (unless `include_usd` is false) and every rigspace rule.

    Findings are sorted by severity, prim and validator. A rigspace validator plugin that
    fails to load is reported as a warning; a rule that raises is our bug and re-raises.
    """
    specs, failed = rules()
    validators = register(specs)
    if include_usd:
        validators += [
            v
            for v in UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
            if not v.GetMetadata().isSuite and not str(v.GetMetadata().name).startswith(PREFIX)
        ]
    _failures.clear()
    _blocks.clear()
    findings = []
    try:
        errors = UsdValidation.ValidationContext(validators).Validate(stage)
    except Tf.ErrorException as exc:  # a USD validator that trips over an unreadable layer
        errors = _validate_without_usd(validators, stage)
        findings.append(_validators_failed(exc))
    if _failures:
        raise _failures[0]
    findings += [_finding(e) for e in errors if not e.HasNoError()]
    findings += [
        Finding(WARNING, PREFIX + "plugins", "PluginFailed", "", f"validator plugin {n!r}: {why}")
        for n, why in failed.items()
    ]
    order = {ERROR: 0, WARNING: 1}
    return sorted(findings, key=lambda f: (order[f.severity], f.prim, f.validator, f.code))


def _validate_without_usd(
    validators: list[UsdValidation.Validator], stage: Usd.Stage
) -> list[UsdValidation.ValidationError]:
    """Run rigspace's own validators alone (after USD's stopped on the stage), afresh."""
    own = [v for v in validators if str(v.GetMetadata().name).startswith(PREFIX)]
    _failures.clear()
    _blocks.clear()
    return UsdValidation.ValidationContext(own).Validate(stage)


def _validators_failed(exc: Tf.ErrorException) -> Finding:
    """The warning that USD's own validators stopped, with the first line of their error."""
    first = next((line.strip() for line in str(exc).splitlines() if line.strip()), "")
    first = re.sub(r"^Error in '.*?' at line \d+ in file \S+ : ", "", first).strip(" '")
    return Finding(
        WARNING,
        "usd",
        "ValidatorsFailed",
        "",
        f"USD's own validators stopped on this stage ({first[:300]}); rigspace's rules "
        "ran without them.",
    )


def _finding(e: UsdValidation.ValidationError) -> Finding:
    """A USD validation error as a Finding, with the blocks its rule recorded for it."""
    prim = _site_path(e)
    code, message = str(e.GetName()), e.GetMessage()
    return Finding(
        severity=ERROR if e.GetType() == UsdValidation.ValidationErrorType.Error else WARNING,
        validator=str(e.GetValidator().GetMetadata().name) if e.GetValidator() else "",
        code=code,
        prim=prim,
        message=message,
        blocks=_blocks.get((code, prim or "/", message), ()),
    )


# ---------------------------------------------------------------------------------------
# Refusing what a command cannot use


_warned: set[tuple[str, str]] = set()


def _read_prims(stage: Usd.Stage, prims: Sequence[Usd.Prim] | None) -> list[Usd.Prim]:
    """The prims a command reads: every prim, or the given characters and their skinned and
    point-cached meshes (their textures are read too)."""
    if prims is None:
        return list(stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    read = []
    for prim in prims:
        read.append(prim)
        if schema.is_neural_character(prim):
            found, _ = resolve_character(prim)
            if found is not None:
                read += [query.GetPrim() for query in found.skel.skinning]
                read += found.cached
    return read


def require_valid(
    stage: Usd.Stage,
    purpose: str,
    prims: Sequence[Usd.Prim] | None = None,
    *,
    exception: type[RigspaceError] = SceneError,
    warn: Callable[[str], None] | None = None,
) -> None:
    """Refuse a scene that `purpose` ("capture" or "render") cannot use, in inspect's words.

    Runs the stage rules and, on `prims` (None: every prim of the stage; a neural character
    brings its skinned meshes), the rigspace rules whose errors stop `purpose`; raises one
    `exception` for them (a lone finding keeps its own type, e.g. BundleError).
    Warnings go to `warn` (default: stderr, once per stage and message).
    """
    if purpose not in PURPOSES:
        raise ValueError(f"purpose must be one of {PURPOSES}, got {purpose!r}")
    specs, _failed = rules()
    errors: list[Issue] = []
    targets = _read_prims(stage, prims)
    for spec in specs:
        if purpose not in spec.purposes:
            continue
        for prim in [stage.GetPseudoRoot()] if spec.stage else targets:
            for issue in spec.check(prim):
                if purpose not in (spec.purposes if issue.purposes is None else issue.purposes):
                    continue
                if issue.severity == ERROR:
                    errors.append(issue)
                elif warn is not None:
                    warn(issue.message)
                elif (stage.GetRootLayer().identifier, issue.message) not in _warned:
                    _warned.add((stage.GetRootLayer().identifier, issue.message))
                    print(f"rigspace {purpose}: warning: {issue.message}", file=sys.stderr)
    _refuse(stage, purpose, errors, exception)


def require_readable(
    stage: Usd.Stage, purpose: str, *, exception: type[RigspaceError] = SceneError
) -> None:
    """Refuse a stage with a layer USD cannot read (a sublayer, reference or payload: inspect's
    UnreadableLayer, in its words), before `purpose` looks for what such a layer may hold. USD
    composes around it, so a character or a camera in it looks simply absent: capture said
    "0 neural characters ... pass --character" and render "The stage has no Camera prim"."""
    _refuse(stage, purpose, list(unreadable_layer_issues(stage)), exception)


def _refuse(
    stage: Usd.Stage, purpose: str, errors: list[Issue], exception: type[RigspaceError]
) -> None:
    """Raise the error of a lone issue, or one `exception` listing them; nothing for none."""
    if len(errors) == 1:
        raise errors[0].as_error(exception)
    if errors:
        name = stage.GetRootLayer().identifier
        raise exception(
            f"Scene {name} has {len(errors)} problems that stop {purpose}:\n"
            + "\n".join(f"  - {issue.message}" for issue in errors)
            + "\n",
            f"fix each as it says (`rigspace inspect {name}` lists them all).",
        )
