"""Typed, lazy, strict plugin registries (victims and attacks; datasets later).

A :class:`Registry` maps names to targets of one type ``T``. Targets arrive three ways:

* in-tree decoration: ``@REG.register("name")`` on an object, or ``REG.register("name", obj)``;
* a lazy ``"package.module:attr"`` string, imported on the first :meth:`Registry.get`;
* installed plugins: every entry point of the registry's group (e.g. ``robustbench3d.victims``)
  in any installed distribution, discovered on the first lookup and loaded on the first ``get``.

Rules: re-registering a name with the *same* target is a no-op, with a different target it raises
:class:`RegistryError`; an unknown name raises :class:`UnknownNameError` with close matches ("did
you mean"); a distribution found twice on ``sys.path`` (the classic duplicate ``dist-info`` /
``egg-info`` of an editable install) contributes its entry points once; an entry point whose name
is not a valid registry name is rejected with a message naming its distribution
(:meth:`Registry.rejected`, and the error of a lookup of that name); a plugin that fails to import
raises :class:`PluginImportError` naming the distribution, the entry point and the exception;
setting the environment variable ``ROBUSTBENCH3D_NO_PLUGINS=1`` disables entry-point discovery
altogether.

References: what a user types for a target (``run --victims``/``--attacks``, ``attack apply OBJECT``, the keys of
``--victim-arg``/``--attack-arg``) is a *reference*, turned into a registered name by :meth:`Registry.resolve`
(the one resolver of victims and attacks alike). A name passes through; a reference that names a file or a
directory is claimed by one of the registry's *path resolvers* (``"module:function"``, like the loaders: an ONNX
victim directory, an object file ``NAME.ply``), which registers it for this process under a name derived from
the path (:func:`sanitise_name`) with :meth:`Registry.register_reference`. Factory arguments ``NAME:KEY=VALUE``
(and ``KEY=VALUE``) are parsed by :func:`parse_factory_args` (and :func:`parse_kwargs`).

Targets are typically :class:`Spec` objects (a factory plus whatever metadata the kind of target
declares: :class:`robustbench3d.victims.spec.VictimSpec`, :class:`robustbench3d.attacks.spec.AttackSpec`).
This module knows no kind of target and imports only the standard library.
"""

from __future__ import annotations

import difflib
import fnmatch
import importlib
import json
import os
import re
import threading
import unicodedata
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from importlib import metadata as importlib_metadata
from typing import Any, Generic, TypeVar, cast, overload

from robustbench3d.errors import RobustBenchError

T = TypeVar("T")
F = TypeVar("F")

#: Environment variable: any value other than "", "0", "false", "no" disables plugin discovery.
NO_PLUGINS_ENV = "ROBUSTBENCH3D_NO_PLUGINS"

_NAME = re.compile(r"^[a-z0-9][a-z0-9._-]*$")
_INVALID = re.compile(r"[^a-z0-9._-]+")


class RegistryError(RobustBenchError, ValueError):
    """Invalid registration (bad name, collision) or a target that fails to load or validate."""


class PluginImportError(RegistryError):
    """An installed plugin's entry point failed to import (the plugin is broken, not the call)."""


class UnknownNameError(RobustBenchError, LookupError):
    """A name that is not registered; the message suggests close matches."""

    def __init__(self, kind: str, name: str, known: list[str]):
        self.name = name
        self.suggestions = difflib.get_close_matches(name, known, n=3, cutoff=0.6)
        hint = f"; did you mean {', '.join(repr(s) for s in self.suggestions)}?" if self.suggestions else ""
        listing = f" (registered: {', '.join(known)})" if known and not self.suggestions else ""
        super().__init__(f"unknown {kind} {name!r}{hint}{listing}")


@dataclass(frozen=True)
class Spec(Generic[F]):
    """A registrable factory: ``spec.create(**kwargs)`` builds the object. Subclasses add the
    metadata of their kind of target and may check what ``create`` builds."""

    factory: Callable[..., F]

    def create(self, **kwargs: Any) -> F:
        return self.factory(**kwargs)

    @property
    def key(self) -> str:
        """Identity used to tell a re-registration of the same factory from a collision."""
        return _qualified_name(self.factory) or f"id:{id(self.factory)}"


@dataclass
class Entry(Generic[T]):
    """One registry slot. ``target`` is the loaded object once :attr:`loaded` is True."""

    name: str
    target: Any  # T, a "module:attr" str, or an importlib.metadata.EntryPoint
    origin: str  # "in-tree", "lazy module:attr", "plugin <dist> <version>", or the registrant's own
    loaded: bool = False
    conflict: str | None = None  # set when two plugins claim the name; raised on get()
    dist: str | None = None  # the distribution of a plugin entry

    @property
    def pending(self) -> str | None:
        """The reference still to be imported, or None when loaded."""
        if self.loaded:
            return None
        return self.target if isinstance(self.target, str) else str(self.target.value)


def _qualified_name(obj: Any) -> str | None:
    mod, qual = getattr(obj, "__module__", None), getattr(obj, "__qualname__", None)
    return f"{mod}:{qual}" if mod and qual else None


def plugins_disabled() -> bool:
    """True when ``$ROBUSTBENCH3D_NO_PLUGINS`` disables entry-point discovery."""
    return os.environ.get(NO_PLUGINS_ENV, "").strip().lower() not in ("", "0", "false", "no")


def _split_reference(ref: str) -> tuple[str, str]:
    module_name, sep, attr = ref.partition(":")
    if not sep or not module_name or not attr:
        raise RegistryError(f"lazy target {ref!r} must look like 'package.module:attr'")
    return module_name, attr


def import_reference(ref: str) -> Any:
    """Import ``"package.module:attr.sub"`` and return the attribute."""
    module_name, attr = _split_reference(ref)
    obj: Any = importlib.import_module(module_name)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def sanitise_name(text: str) -> str:
    """A registry name from free text (a directory or file name): NFKD-folded to ASCII with accents
    dropped, lowercase, runs of other characters -> "-". "" when nothing is left or when a letter
    or digit has no ASCII form (the name would not be readable)."""
    folded = []
    for ch in unicodedata.normalize("NFKD", text):
        if ch.isascii():
            folded.append(ch)
        elif unicodedata.category(ch)[0] in "LN":
            return ""
        elif not unicodedata.combining(ch):
            folded.append(" ")  # a non-ASCII symbol or space separates words
    return _INVALID.sub("-", "".join(folded).lower()).strip("-._")


def parse_value(raw: str) -> Any:
    """A factory argument's VALUE: parsed as JSON when it is valid JSON (numbers, true/false, null, lists),
    else kept as the string (paths)."""
    try:
        return json.loads(raw)
    except json.JSONDecodeError:
        return raw


def parse_kwargs(items: list[str] | None, option: str, example: str = "weights=cascade.pt") -> dict[str, Any]:
    """``["KEY=VALUE", ...]`` -> ``{KEY: VALUE}`` (VALUE: :func:`parse_value`); an item without ``=`` or
    without a key raises :class:`RobustBenchError` naming ``option`` and the item."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, eq, raw = item.partition("=")
        if not eq or not key.strip():
            raise RobustBenchError(f"{option} {item!r}: expected KEY=VALUE (e.g. {example})")
        out[key.strip()] = parse_value(raw)
    return out


def parse_factory_args(items: list[str] | None, option: str,
                       example: str = "fpointnet-v1:weights=cascade.pt") -> dict[str, dict[str, Any]]:
    """``["NAME:KEY=VALUE", ...]`` -> ``{NAME: {KEY: VALUE}}`` (VALUE: :func:`parse_value`); NAME is a
    reference, resolved later (:meth:`Registry.resolve_all`). A malformed item raises
    :class:`RobustBenchError` naming ``option`` and the item."""
    out: dict[str, dict[str, Any]] = {}
    for item in items or []:
        name, sep, assignment = item.partition(":")
        key, eq, raw = assignment.partition("=")
        if not sep or not eq or not name.strip() or not key.strip():
            raise RobustBenchError(f"{option} {item!r}: expected NAME:KEY=VALUE (e.g. {example})")
        out.setdefault(name.strip(), {})[key.strip()] = parse_value(raw)
    return out


def _normalize_dist(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


class Registry(Generic[T]):
    """Name -> target registry with lazy targets and entry-point plugins.

    Args:
        kind: what is registered, used in messages ("victim", "attack").
        group: entry-point group scanned for plugins, or None for no plugins.
        base: if given, every loaded target must be an instance (or subclass) of it.
        key: identity of a loaded target for the same-target check (default: the object itself;
            :class:`Spec` targets compare by factory).
        modules: in-tree modules imported on the first lookup (their decorators register).
        loaders: ``"module:function"`` references called (no arguments) on the first lookup, after
            ``modules``: registrations read from files happen on first use, not at import.
        path_resolvers: ``"module:function"`` references of the functions :meth:`resolve` asks, in order,
            about a reference: ``function(reference) -> name | None``; one that claims it (a file or
            directory of its kind) registers it (:meth:`register_reference`) and returns the name.
    """

    def __init__(self, kind: str, *, group: str | None = None, base: type | None = None,
                 key: Callable[[Any], Any] | None = None, modules: tuple[str, ...] = (),
                 loaders: tuple[str, ...] = (), path_resolvers: tuple[str, ...] = ()):
        self.kind = kind
        self.group = group
        self.base = base
        self._key = key
        self._modules = modules
        self._loaders = loaders
        self._path_resolvers = path_resolvers
        self._entries: dict[str, Entry[T]] = {}
        self._rejected: dict[str, str] = {}  # invalid entry-point name -> why it was rejected
        self._lock = threading.RLock()
        self._discovered = False
        self._frozen = False

    # ---- registration ------------------------------------------------------------------
    @overload
    def register(self, name: str, target: None = None, *, origin: str | None = None) -> Callable[[T], T]: ...
    @overload
    def register(self, name: str, target: T | str, *, origin: str | None = None) -> T | str: ...

    def register(self, name: str, target: Any = None, *, origin: str | None = None) -> Any:
        """Register ``target`` (an object or a lazy ``"module:attr"`` string) under ``name``.

        Without ``target`` returns a decorator that registers the decorated object and returns it
        unchanged. ``origin`` overrides the listed origin ("in-tree" or "lazy module:attr").
        Raises :class:`RegistryError` on a bad name, on a frozen registry, or when the name is
        taken by a different target.
        """
        if target is None:
            def decorator(obj: T) -> T:
                self.register(name, obj, origin=origin)
                return obj
            return decorator
        origin = origin or (f"lazy {target}" if isinstance(target, str) else "in-tree")
        if isinstance(target, str):
            _split_reference(target)
        else:
            self._validate(name, target)
        self._add(Entry(name=name, target=target, origin=origin, loaded=not isinstance(target, str)))
        return target

    def _add(self, entry: Entry[T]) -> None:
        if not _NAME.match(entry.name):
            raise RegistryError(f"{self.kind} name {entry.name!r} must match {_NAME.pattern}")
        with self._lock:
            if self._frozen:
                raise RegistryError(f"{self.kind} registry is frozen; cannot register {entry.name!r}")
            old = self._entries.get(entry.name)
            if old is None:
                self._entries[entry.name] = entry
            elif not self._same(old, entry):
                raise RegistryError(
                    f"{self.kind} name {entry.name!r} is already registered ({old.origin}) with a different "
                    f"target than the new one ({entry.origin}); choose another name")

    def _same(self, a: Entry[T], b: Entry[T]) -> bool:
        if a.pending is not None and b.pending is not None:
            return a.pending == b.pending
        ta, tb = self._load(a), self._load(b)
        return ta is tb or self._identity(ta) == self._identity(tb)

    def _identity(self, obj: Any) -> Any:
        if self._key is not None:
            return self._key(obj)
        return id(obj)

    def unregister(self, name: str) -> None:
        """Remove ``name`` (e.g. a user registration that was deleted); unknown names raise."""
        with self._lock:
            if self._frozen:
                raise RegistryError(f"{self.kind} registry is frozen; cannot unregister {name!r}")
            self.entry(name)
            del self._entries[name]

    def register_reference(self, name: str, target: T, *, origin: str, taken: str) -> str:
        """Register ``target``, built from a path reference, under ``name`` for this process and return
        ``name``. The registry's own entries (in-tree, loaded, plugins) are discovered first, so they take
        precedence: a name they hold, or that holds another target, raises :class:`RobustBenchError` with the
        message ``taken``; the same target again is a no-op."""
        self._discover()
        try:
            self.register(name, target, origin=origin)
        except RegistryError:
            raise RobustBenchError(taken) from None
        return name

    def freeze(self) -> None:
        """Make the registry read-only (after discovery)."""
        with self._lock:
            self._discover()
            self._frozen = True

    # ---- references ---------------------------------------------------------------------
    def resolve(self, reference: str) -> str:
        """The registered name ``reference`` stands for (module doc, "References"): the name a path
        resolver registered it under, or ``reference`` itself (a name: looked up when it is used, so an
        unknown one fails there, with did-you-mean)."""
        for resolver in self._path_resolvers:
            name = import_reference(resolver)(reference)
            if name is not None:
                return str(name)
        return reference

    def resolve_all(self, references: list[str],
                    args: Mapping[str, Mapping[str, Any]]) -> tuple[list[str], dict[str, dict[str, Any]]]:
        """:meth:`resolve` of each reference, and ``args`` (factory arguments per reference, e.g. from
        :func:`parse_factory_args`) keyed by the resolved names: a path given both ways stays one target."""
        return ([self.resolve(r) for r in references],
                {self.resolve(k): dict(v) for k, v in args.items()})

    # ---- lookup -------------------------------------------------------------------------
    def get(self, name: str) -> T:
        """The target registered under ``name``, importing it on first use."""
        self._discover()
        with self._lock:
            entry = self._entries.get(name)
            if entry is None:
                raise self._unknown(name)
            if entry.conflict is not None:
                raise RegistryError(entry.conflict)
            return self._load(entry)

    def __getitem__(self, name: str) -> T:
        return self.get(name)

    def entry(self, name: str) -> Entry[T]:
        """The raw entry (not loaded)."""
        self._discover()
        with self._lock:
            if name not in self._entries:
                raise self._unknown(name)
            return self._entries[name]

    def rejected(self) -> list[str]:
        """Why each installed entry point with an invalid name was ignored (one message each)."""
        self._discover()
        with self._lock:
            return [self._rejected[k] for k in sorted(self._rejected)]

    def names(self, pattern: str = "*") -> list[str]:
        """Sorted registered names matching a glob pattern (nothing is imported)."""
        self._discover()
        with self._lock:
            return sorted(n for n in self._entries if fnmatch.fnmatchcase(n, pattern))

    def items(self, pattern: str = "*") -> Iterator[tuple[str, T]]:
        """(name, loaded target) pairs; loads every matching entry."""
        for name in self.names(pattern):
            yield name, self.get(name)

    def __contains__(self, name: object) -> bool:
        self._discover()
        return name in self._entries

    def __len__(self) -> int:
        self._discover()
        return len(self._entries)

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    # ---- internals ---------------------------------------------------------------------
    def _unknown(self, name: str) -> RegistryError | UnknownNameError:
        """The error for a name that is not registered: a rejected entry point's reason, if the
        name is (the lowercase of) one, else :class:`UnknownNameError` with suggestions."""
        for raw, why in self._rejected.items():
            if name in (raw, raw.lower()):
                return RegistryError(why)
        return UnknownNameError(self.kind, name, sorted(self._entries))

    def _load(self, entry: Entry[T]) -> T:
        with self._lock:
            if entry.loaded:
                return cast(T, entry.target)
            ref = entry.target
            try:
                obj = import_reference(ref) if isinstance(ref, str) else ref.load()
            except RegistryError:
                raise
            except Exception as exc:
                if entry.dist is not None:
                    raise PluginImportError(
                        f"{self.kind} {entry.origin} failed to import: its entry point "
                        f"'{entry.name} = {entry.pending}' ({self.group}) raised {exc.__class__.__name__}: {exc}; "
                        f"reinstall or fix the plugin package {entry.dist!r}, or uninstall it (or set "
                        f"{NO_PLUGINS_ENV}=1 to disable plugins)") from exc
                raise RegistryError(
                    f"cannot load {self.kind} {entry.name!r} from {entry.pending} ({entry.origin}): "
                    f"{exc.__class__.__name__}: {exc}") from exc
            self._validate(entry.name, obj, entry.origin)
            entry.target, entry.loaded = obj, True
            return cast(T, obj)

    def _validate(self, name: str, obj: Any, origin: str = "in-tree") -> None:
        if self.base is None:
            return
        ok = isinstance(obj, self.base) or (isinstance(obj, type) and issubclass(obj, self.base))
        if not ok:
            raise RegistryError(f"{self.kind} {name!r} ({origin}) is a {type(obj).__name__}, "
                                f"expected a {self.base.__name__}")

    def _discover(self) -> None:
        if self._discovered:
            return
        with self._lock:
            if self._discovered:
                return
            self._discovered = True  # set first: imported modules may call register()
            for module in self._modules:
                importlib.import_module(module)
            for loader in self._loaders:
                import_reference(loader)()
            if self.group is not None and not plugins_disabled():
                self._discover_entry_points()

    def _discover_entry_points(self) -> None:
        seen: set[tuple[str, str]] = set()
        for ep in importlib_metadata.entry_points(group=self.group or ""):
            dist = getattr(ep, "dist", None)
            dist_name = _normalize_dist(dist.metadata["Name"]) if dist is not None else "?"
            version = dist.version if dist is not None else "?"
            # The same distribution found twice on sys.path (dist-info + egg-info): keep the first.
            if (dist_name, ep.name) in seen:
                continue
            seen.add((dist_name, ep.name))
            entry: Entry[T] = Entry(name=ep.name, target=ep, origin=f"plugin {dist_name} {version}", dist=dist_name)
            if not _NAME.match(ep.name):  # not addressable: reject it, naming who ships it
                self._rejected[ep.name] = self._rejection(ep.name, ep.value, dist_name, version)
                continue
            old = self._entries.get(ep.name)
            if old is None:
                self._entries[ep.name] = entry
            elif old.pending != entry.pending or old.loaded:
                old.conflict = self._clash(old, entry)

    def _clash(self, old: Entry[T], new: Entry[T]) -> str:
        """The error of a name claimed by an entry point (``new``) and by ``old``: another plugin, or an
        in-tree / registered entry. It says who must act: a factory argument cannot resolve it."""
        claim = f"{new.origin} (entry point '{new.name} = {new.pending}' of group {self.group})"
        if old.dist is not None:
            return (f"{self.kind} name {new.name!r} is claimed by both {old.origin} ({old.pending}) and {claim}; "
                    f"uninstall one of {old.dist!r} and {new.dist!r}, or set {NO_PLUGINS_ENV}=1 to disable plugins")
        return (f"{self.kind} name {new.name!r} is claimed by both the {old.origin} {self.kind} and {claim}, so "
                f"neither is used; the plugin must rename its entry point: until it does, uninstall {new.dist!r} "
                f"(or set {NO_PLUGINS_ENV}=1 to disable plugins)")

    def _rejection(self, name: str, value: str, dist_name: str, version: str) -> str:
        fixed = re.sub(r"[^a-z0-9._-]+", "-", name.lower()).strip("-._")
        hint = f" (e.g. {fixed!r})" if _NAME.match(fixed) else ""
        return (f"plugin {dist_name!r} {version}: entry point {name!r} (= {value}) of group {self.group} is not a "
                f"valid {self.kind} name (lowercase letters, digits, '.', '_', '-', starting with a letter or "
                f"digit), so it is ignored; the plugin must rename it{hint}")


__all__ = [
    "NO_PLUGINS_ENV", "Entry", "PluginImportError", "Registry", "RegistryError", "Spec", "UnknownNameError",
    "import_reference", "parse_factory_args", "parse_kwargs", "parse_value", "plugins_disabled", "sanitise_name",
]
