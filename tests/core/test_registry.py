"""Registry semantics: decorator and lazy registration, collisions, did-you-mean, entry points
(through fake installed distributions written to a temporary sys.path entry), duplicate
distributions, the disable switch, metadata validation; references (names and paths) resolved by the
registry's path resolvers, and factory arguments ``NAME:KEY=VALUE`` / ``KEY=VALUE``."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from robustbench3d.errors import RobustBenchError
from robustbench3d.registry import (
    NO_PLUGINS_ENV,
    Registry,
    RegistryError,
    Spec,
    UnknownNameError,
    parse_factory_args,
    parse_kwargs,
)

GROUP = "robustbench3d.test_plugins"


class Thing:
    def __init__(self, label: str):
        self.label = label


def write_module(root: Path, name: str, body: str) -> None:
    (root / f"{name}.py").write_text(textwrap.dedent(body))


def write_dist(root: Path, dist: str, version: str, entry_points: dict[str, str], kind: str = "dist-info") -> None:
    """A minimal installed distribution (metadata + entry_points.txt) under ``root``."""
    norm = dist.replace("-", "_")
    meta_dir = root / (f"{norm}-{version}.dist-info" if kind == "dist-info" else f"{norm}.egg-info")
    meta_dir.mkdir(parents=True)
    (meta_dir / ("METADATA" if kind == "dist-info" else "PKG-INFO")).write_text(
        f"Metadata-Version: 2.1\nName: {dist}\nVersion: {version}\n")
    lines = [f"[{GROUP}]"] + [f"{k} = {v}" for k, v in entry_points.items()]
    (meta_dir / "entry_points.txt").write_text("\n".join(lines) + "\n")


@pytest.fixture
def plugin_path(tmp_path, monkeypatch) -> Path:
    """A fresh sys.path entry with unique module names per test."""
    root = tmp_path / "site"
    root.mkdir()
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.delenv(NO_PLUGINS_ENV, raising=False)
    return root


def test_decorator_rejects_wrong_type_and_registers_right_type():
    reg: Registry[object] = Registry("thing", base=Thing)
    with pytest.raises(RegistryError, match="expected a Thing"):
        reg.register("alpha", object())
    a = Thing("a")
    assert reg.register("alpha", a) is a
    assert reg.get("alpha") is a and reg["alpha"] is a
    assert "alpha" in reg and len(reg) == 1 and reg.names() == ["alpha"]

    @reg.register("beta")
    class Sub(Thing):  # classes deriving from the base are accepted too
        pass

    assert reg.get("beta") is Sub
    assert reg.names("b*") == ["beta"]


def test_lazy_string_is_imported_on_first_get_only(plugin_path):
    write_module(plugin_path, "rb3d_lazy_mod_a", """
        THING = {"label": "lazy"}
    """)
    reg: Registry[dict] = Registry("thing", base=dict)
    reg.register("lazy", "rb3d_lazy_mod_a:THING")
    assert "rb3d_lazy_mod_a" not in sys.modules
    assert reg.names() == ["lazy"] and reg.entry("lazy").pending == "rb3d_lazy_mod_a:THING"
    assert "rb3d_lazy_mod_a" not in sys.modules
    assert reg.get("lazy")["label"] == "lazy"
    assert "rb3d_lazy_mod_a" in sys.modules and reg.entry("lazy").loaded


def test_lazy_string_errors():
    reg: Registry[Thing] = Registry("thing")
    with pytest.raises(RegistryError, match="module:attr"):
        reg.register("bad", "no_colon_here")
    reg.register("missing", "rb3d_no_such_module_xyz:THING")
    with pytest.raises(RegistryError, match="cannot load thing 'missing'"):
        reg.get("missing")


def test_collision_with_a_different_target_raises_same_target_is_noop(plugin_path):
    reg: Registry[Thing] = Registry("thing")
    a, b = Thing("a"), Thing("b")
    reg.register("x", a)
    reg.register("x", a)  # idempotent
    with pytest.raises(RegistryError, match="already registered"):
        reg.register("x", b)
    assert reg.get("x") is a
    reg.register("y", "pkg.mod:A")
    reg.register("y", "pkg.mod:A")
    with pytest.raises(RegistryError, match="already registered"):
        reg.register("y", "pkg.mod:B")
    # a lazy reference and the object it resolves to are the same target
    write_module(plugin_path, "rb3d_lazy_mod_b", """
        THING = {"label": "z"}
    """)
    reg.register("z", "rb3d_lazy_mod_b:THING")
    import rb3d_lazy_mod_b

    reg.register("z", rb3d_lazy_mod_b.THING)


def test_bad_names_and_frozen():
    reg: Registry[Thing] = Registry("thing")
    for bad in ("", "Upper", "with space", "-lead"):
        with pytest.raises(RegistryError, match="must match"):
            reg.register(bad, Thing("t"))
    reg.freeze()
    with pytest.raises(RegistryError, match="frozen"):
        reg.register("late", Thing("t"))


def test_unknown_name_suggests_close_matches():
    reg: Registry[Thing] = Registry("victim")
    for name in ("fpointnet-v1", "fpointnet-v1-lite", "pointpillars"):
        reg.register(name, Thing(name))
    with pytest.raises(UnknownNameError) as exc:
        reg.get("fpointnet-v2")
    assert "did you mean" in str(exc.value)
    assert exc.value.suggestions[0] in ("fpointnet-v1", "fpointnet-v1-lite")
    assert isinstance(exc.value, LookupError)
    with pytest.raises(UnknownNameError, match="registered: fpointnet-v1, fpointnet-v1-lite, pointpillars"):
        reg.get("zzz")


def test_entry_points_are_discovered_lazily(plugin_path):
    write_module(plugin_path, "rb3d_fake_plugin_a", """
        THING = {"label": "from plugin"}
    """)
    write_dist(plugin_path, "rb3d-fake-plugin-a", "1.2.3", {"fake-a": "rb3d_fake_plugin_a:THING"})
    reg: Registry[dict] = Registry("thing", group=GROUP, base=dict)
    assert reg.names() == ["fake-a"]
    entry = reg.entry("fake-a")
    assert entry.origin == "plugin rb3d-fake-plugin-a 1.2.3" and not entry.loaded
    assert "rb3d_fake_plugin_a" not in sys.modules
    assert reg.get("fake-a")["label"] == "from plugin"
    assert reg.entry("fake-a").loaded


def test_same_distribution_twice_on_path_loads_once(plugin_path, tmp_path, monkeypatch):
    """dist-info in one sys.path entry and egg-info of the same project in another (the
    editable-install pitfall) must give one entry, not a collision."""
    write_module(plugin_path, "rb3d_fake_plugin_b", """
        THING = {"label": "b"}
    """)
    write_dist(plugin_path, "rb3d-fake-plugin-b", "0.1", {"fake-b": "rb3d_fake_plugin_b:THING"})
    other = tmp_path / "source_tree"
    write_dist(other, "rb3d_fake_plugin_b", "0.1", {"fake-b": "rb3d_fake_plugin_b:THING"}, kind="egg-info")
    monkeypatch.syspath_prepend(str(other))
    reg: Registry[dict] = Registry("thing", group=GROUP)
    assert reg.names() == ["fake-b"]
    assert reg.get("fake-b")["label"] == "b"


def test_two_distributions_claiming_one_name_raise_on_get(plugin_path):
    write_module(plugin_path, "rb3d_fake_plugin_c", """
        ONE = {"label": "one"}
        TWO = {"label": "two"}
    """)
    write_dist(plugin_path, "rb3d-fake-c-one", "1.0",
               {"clash": "rb3d_fake_plugin_c:ONE", "ok": "rb3d_fake_plugin_c:ONE"})
    write_dist(plugin_path, "rb3d-fake-c-two", "1.0", {"clash": "rb3d_fake_plugin_c:TWO"})
    reg: Registry[dict] = Registry("thing", group=GROUP)
    assert reg.names() == ["clash", "ok"]
    with pytest.raises(RegistryError, match="claimed by both"):
        reg.get("clash")
    assert reg.get("ok")["label"] == "one"  # one bad name does not break the others


def test_plugin_colliding_with_in_tree_name_raises(plugin_path):
    write_module(plugin_path, "rb3d_fake_plugin_d", """
        THING = {"label": "plugin"}
    """)
    write_dist(plugin_path, "rb3d-fake-plugin-d", "1.0", {"taken": "rb3d_fake_plugin_d:THING"})
    reg: Registry[dict] = Registry("thing", group=GROUP)
    reg.register("taken", {"label": "in-tree"})
    with pytest.raises(RegistryError, match="claimed by both"):
        reg.get("taken")


def test_env_var_disables_plugins(plugin_path, monkeypatch):
    write_module(plugin_path, "rb3d_fake_plugin_e", "THING = 1\n")
    write_dist(plugin_path, "rb3d-fake-plugin-e", "1.0", {"fake-e": "rb3d_fake_plugin_e:THING"})
    monkeypatch.setenv(NO_PLUGINS_ENV, "1")
    assert Registry("thing", group=GROUP).names() == []
    monkeypatch.setenv(NO_PLUGINS_ENV, "0")
    assert Registry("thing", group=GROUP).names() == ["fake-e"]


def test_spec_creates_through_its_factory_and_is_identified_by_it():
    spec = Spec(factory=Thing)
    made = spec.create(label="x")
    assert isinstance(made, Thing) and made.label == "x"
    assert spec.key == f"{__name__}:Thing"
    reg: Registry[Spec[Thing]] = Registry("thing", base=Spec, key=lambda s: s.key)
    reg.register("t", Spec(factory=Thing))
    reg.register("t", Spec(factory=Thing))  # the same factory again: a no-op
    with pytest.raises(RegistryError, match="already registered"):
        reg.register("t", Spec(factory=dict))


def test_references_resolve_names_and_paths_through_the_path_resolvers(plugin_path, tmp_path):
    write_module(plugin_path, "rb3d_refs_a", """
        from pathlib import Path

        from robustbench3d.registry import Registry, sanitise_name

        REG = Registry("thing", base=dict, key=lambda t: t["path"],
                       path_resolvers=("rb3d_refs_a:nothing", "rb3d_refs_a:thing_file"))
        asked = []

        def nothing(reference):
            asked.append(reference)
            return None

        def thing_file(reference):
            if not reference.endswith(".thing"):
                return None
            path = Path(reference).resolve()
            name = sanitise_name(path.stem)
            return REG.register_reference(name, {"path": str(path)}, origin="thing file",
                                          taken=f"--things {reference}: {name!r} is taken")
    """)
    import rb3d_refs_a

    reg = rb3d_refs_a.REG
    reg.register("taken", {"path": "elsewhere"})
    assert reg.resolve("plain-name") == "plain-name" and "plain-name" not in reg  # a name: looked up when used
    first = tmp_path / "Mÿ Fïle.thing"
    assert reg.resolve(str(first)) == "my-file"  # folded to ASCII, lowercase, "-" between words
    assert reg.entry("my-file").origin == "thing file" and reg.get("my-file") == {"path": str(first.resolve())}
    assert reg.resolve(str(first)) == "my-file"  # the same file again: the same entry
    assert rb3d_refs_a.asked == ["plain-name", str(first), str(first)]  # every reference asked, in order
    with pytest.raises(RobustBenchError, match=r"^--things .*taken\.thing: 'taken' is taken$"):
        reg.resolve(str(tmp_path / "taken.thing"))  # the registry's own entries take precedence
    with pytest.raises(RobustBenchError, match="'my-file' is taken"):
        reg.resolve(str(tmp_path / "sub" / "my file.thing"))  # another file under the same name
    names, args = reg.resolve_all(["plain-name", str(first)], {str(first): {"k": 1}, "plain-name": {"j": 2}})
    assert names == ["plain-name", "my-file"] and args == {"my-file": {"k": 1}, "plain-name": {"j": 2}}


def test_factory_arguments_are_name_key_value_with_json_values():
    items = ["fpointnet-v1:weights=runs/c.pt", "fpointnet-v1:num_points=1024", "adv-object:eot=true",
             "adv-object:range=[0.1, 0.2]", "my.ply:path=C:/x=y", " spaced : key = null", "a:empty="]
    assert parse_factory_args(items, "--victim-arg") == {
        "fpointnet-v1": {"weights": "runs/c.pt", "num_points": 1024},
        "adv-object": {"eot": True, "range": [0.1, 0.2]},
        "my.ply": {"path": "C:/x=y"},  # the first ":" ends the name, the first "=" the key
        "spaced": {"key": None},
        "a": {"empty": ""},
    }
    for bad in ("weights=x.pt", "fpointnet-v1:weights", ":k=1", "v:=1"):
        with pytest.raises(RobustBenchError, match=rf"^--attack-arg '{bad}': expected NAME:KEY=VALUE \(e\.g\. "):
            parse_factory_args(["ok:k=1", bad], "--attack-arg")
    assert parse_kwargs(["weights=a.pt", "seed=3", "allow_untrained=true"], "--victim-arg") == {
        "weights": "a.pt", "seed": 3, "allow_untrained": True}
    with pytest.raises(RobustBenchError, match=r"^--victim-arg 'weights': expected KEY=VALUE \(e\.g\. weights=cascade"):
        parse_kwargs(["weights"], "--victim-arg")
