"""Config schema: defaults, round trips, and errors that name the file and the key."""
from __future__ import annotations

from pathlib import Path

import pytest

from psonurbs.config import FitConfig, SwarmConfig, config_from_dict, load_config
from psonurbs.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]


def write(tmp_path: Path, text: str, name: str = "cfg.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def error_of(tmp_path: Path, text: str) -> str:
    """The error for a config file holding ``text``, its directory shown as ``cfg.yaml``."""
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert str(path) in message  # the file is named
    return message.replace(str(path), "cfg.yaml")


# ---- defaults and round trips ----------------------------------------------

def test_defaults_match_the_spec():
    c = load_config(None)
    assert c == FitConfig()
    assert (c.orders, c.net_size, c.topology, c.strategy) == ((3, 3), (5, 5), "open", "hybrid")
    assert c.swarm == SwarmConfig(particles=40, iterations=300, inertia=0.7, c1=1.5, c2=1.5, seed=7)
    assert c.degrees == (2, 2)
    assert (c.smoothing, c.swarm_points, c.polish_iterations) == (1e-6, 1500, 100)
    assert c.tessellation == (101, 101)
    assert c.weight_bounds == (0.2, 5.0)
    assert (c.min_knot_gap, c.cross_validation, c.robust) == (0.2, True, True)


def test_full_file_is_read_with_paper_names(tmp_path):
    c = load_config(write(tmp_path, """
orders: [4, 3]
net_size: [10, 6]
topology: cylinder
strategy: full
swarm: {particles: 12, iterations: 50, inertia: 0.5, c1: 2, c2: 1.25, seed: 0}
smoothing: 1e-3
swarm_points: 800
polish_iterations: 0
tessellation: [21, 31]
weight_bounds: [0.5, 2]
min_knot_gap: 0.1
cross_validation: false
robust: false
"""))
    assert c.orders == (4, 3) and c.degrees == (3, 2) and c.net_size == (10, 6)
    assert c.topology == "cylinder" and c.strategy == "full"
    assert c.swarm == SwarmConfig(12, 50, 0.5, 2.0, 1.25, 0)
    assert isinstance(c.swarm.c1, float)  # int accepted where a float is expected
    assert c.smoothing == 1e-3  # YAML 1.1 would read "1e-3" as a string
    assert (c.swarm_points, c.polish_iterations, c.tessellation) == (800, 0, (21, 31))
    assert c.weight_bounds == (0.5, 2.0) and c.min_knot_gap == 0.1 and c.cross_validation is False
    assert c.robust is False


def test_remove_outliers_is_another_name_for_robust(tmp_path):
    assert load_config(write(tmp_path, "remove_outliers: false\n")).robust is False
    assert load_config(write(tmp_path, "remove_outliers: true\nrobust: true\n")).robust is True
    assert "remove_outliers" not in load_config(write(tmp_path, "remove_outliers: true\n")).to_dict()
    assert error_of(tmp_path, "remove_outliers: true\nrobust: false\n") == (
        "cfg.yaml: config keys 'remove_outliers' and 'robust' disagree ('remove_outliers' is another name for 'robust')")


def test_to_dict_has_yaml_shape_and_round_trips():
    c = FitConfig(orders=(4, 4), net_size=(8, 9), swarm=SwarmConfig(seed=3))
    d = c.to_dict()
    assert list(d) == ["orders", "net_size", "topology", "strategy", "swarm", "smoothing",
                       "swarm_points", "polish_iterations", "tessellation", "weight_bounds",
                       "min_knot_gap", "cross_validation", "refine", "refine_iterations", "robust",
                       "parametrisation", "trim"]
    assert d["orders"] == [4, 4] and d["net_size"] == [8, 9]
    assert d["swarm"] == {"particles": 40, "iterations": 300, "inertia": 0.7, "c1": 1.5,
                          "c2": 1.5, "seed": 3}
    assert config_from_dict(d) == c


def test_empty_file_gives_defaults(tmp_path):
    assert load_config(write(tmp_path, "# nothing set\n")) == FitConfig()


def test_with_overrides_puts_swarm_keys_in_swarm():
    c = FitConfig().with_overrides(seed=11, particles=9, iterations=None, topology="torus",
                                   **{"swarm.c1": 1.0})
    assert c.swarm == SwarmConfig(particles=9, iterations=300, c1=1.0, seed=11)
    assert c.topology == "torus"
    assert c.orders == (3, 3)


def test_with_overrides_validates_and_names_the_key():
    with pytest.raises(ConfigError, match=r"^command-line options: config key "
                                          r"'swarm.particles': expected a positive integer, got 0$"):
        FitConfig().with_overrides(particles=0)


def test_dataclass_validates_itself():
    with pytest.raises(ConfigError, match="'orders': order 5 in v is larger than net_size 4"):
        FitConfig(orders=(3, 5), net_size=(5, 4))
    assert FitConfig(orders=[4, 4], net_size=[6, 6]).orders == (4, 4)  # lists normalised


@pytest.mark.parametrize("path", sorted((REPO / "configs").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_config_loads(path):
    c = load_config(path)
    assert all(k <= n for k, n in zip(c.orders, c.net_size))


def test_shipped_configs_have_the_documented_values():
    assert load_config(REPO / "configs" / "paper_patch.yaml") == FitConfig()
    patch = load_config(REPO / "configs" / "patch.yaml")
    assert (patch.orders, patch.net_size, patch.topology) == ((4, 4), (8, 8), "open")
    assert patch.swarm == SwarmConfig()


@pytest.mark.parametrize("path", sorted((REPO / "data_samples").glob("*.yaml")),
                         ids=lambda p: p.name)
def test_every_sample_config_loads(path):
    load_config(path)


# ---- errors name the file and the key --------------------------------------

@pytest.mark.parametrize("text, expected", [
    ("swarm:\n  partciles: 3\n",
     "cfg.yaml: unknown config key 'swarm.partciles' (known: particles, iterations, inertia, "
     "c1, c2, seed); did you mean 'swarm.particles'?"),
    ("net_sise: [5, 5]\n", "cfg.yaml: unknown config key 'net_sise'"),
    ("parametrisation: isomap\n",
     "cfg.yaml: config key 'parametrisation': expected one of auto, plane, intrinsic, got 'isomap'"),
    ("swarm:\n  particles: -3\n",
     "cfg.yaml: config key 'swarm.particles': expected a positive integer, got -3"),
    ("swarm:\n  particles: true\n",
     "cfg.yaml: config key 'swarm.particles': expected a positive integer, got true"),
    ("swarm:\n  iterations: 0\n",
     "cfg.yaml: config key 'swarm.iterations': expected a positive integer, got 0"),
    ("swarm:\n  iterations: 10.5\n",
     "cfg.yaml: config key 'swarm.iterations': expected a positive integer, got 10.5"),
    ("swarm:\n  seed: -1\n", "cfg.yaml: config key 'swarm.seed': expected an integer >= 0, got -1"),
    ("swarm:\n  inertia: fast\n",
     "cfg.yaml: config key 'swarm.inertia': expected a finite number >= 0, got 'fast'"),
    ("swarm:\n  c1: .nan\n", "cfg.yaml: config key 'swarm.c1': expected a finite number >= 0, got nan"),
    ("swarm: 40\n", "cfg.yaml: config key 'swarm': expected a mapping, got 40"),
    ("orders: [6, 3]\nnet_size: [5, 5]\n",
     "cfg.yaml: config key 'orders': order 6 in u is larger than net_size 5"),
    ("orders: [3, 3, 3]\n", "cfg.yaml: config key 'orders': expected a list of 2 integers >= 2"),
    ("orders: 3\n", "cfg.yaml: config key 'orders': expected a list of 2 integers >= 2"),
    ("orders: [1, 3]\n", "cfg.yaml: config key 'orders': expected a list of 2 integers >= 2"),
    ("orders: [true, 3]\n", "cfg.yaml: config key 'orders': expected a list of 2 integers >= 2"),
    ("net_size: [5, -5]\n", "cfg.yaml: config key 'net_size': expected a list of 2 positive integers"),
    ("topology: klein\n",
     "cfg.yaml: config key 'topology': expected one of open, cylinder, sphere, torus, auto, "
     "got 'klein'"),
    ("strategy: random\n", "cfg.yaml: config key 'strategy': expected one of hybrid, full"),
    ("smoothing: -1e-3\n", "cfg.yaml: config key 'smoothing': expected a finite number >= 0, "
                           "got -0.001"),
    ("swarm_points: 0\n", "cfg.yaml: config key 'swarm_points': expected an integer >= 16, got 0"),
    ("swarm_points: 15\n", "cfg.yaml: config key 'swarm_points': expected an integer >= 16, got 15"),
    ("polish_iterations: -1\n", "cfg.yaml: config key 'polish_iterations': expected an integer >= 0"),
    ("refine_iterations: -1\n", "cfg.yaml: config key 'refine_iterations': expected an integer >= 0"),
    ("tessellation: [1, 10]\n", "cfg.yaml: config key 'tessellation': expected a list of 2 integers >= 2"),
    ("weight_bounds: [1.5, 5]\n", "cfg.yaml: config key 'weight_bounds': expected [lo, hi] with "
                                  "0 < lo <= 1 <= hi, got [1.5, 5.0]"),
    ("weight_bounds: [0, 5]\n", "cfg.yaml: config key 'weight_bounds': expected a list of 2 "
                                "positive numbers"),
    ("min_knot_gap: 1\n", "cfg.yaml: config key 'min_knot_gap': expected a number in (0, 1), got 1"),
    ("cross_validation: 0.5\n", "cfg.yaml: config key 'cross_validation': expected true or false, got 0.5"),
    ("remove_outliers: 1\n", "cfg.yaml: config key 'remove_outliers': expected true or false, got 1"),
    ("- orders\n- net_size\n", "cfg.yaml: the top level must be a mapping of config keys"),
    ("? [1, 2]\n: 3\n", "malformed YAML in cfg.yaml: a list cannot be a key"),
    ("swarm: {? {a: 1} : 2}\n", "malformed YAML in cfg.yaml: a dict cannot be a key"),
    ("1: 2\n", "cfg.yaml: unknown config key '1'"),
    ("swarm:\n  particles: 1000000000\n", "cfg.yaml: config key 'swarm.particles': 1000000000 is too large: "
                                         "at most 10,000 (particles of the swarm)"),
    ("swarm: {particles: 5000, iterations: 5000}\n", "cfg.yaml: config keys 'swarm.particles' x "
                                                    "'swarm.iterations': 5,000 x 5,000 = 25,000,000 fitness "
                                                    "evaluations is too many: at most 10,000,000"),
    ("net_size: [5, 2000]\n", "cfg.yaml: config key 'net_size': 2000 is too large: at most 1,000"),
    ("tessellation: [3000, 3000]\n", "cfg.yaml: config key 'tessellation': 3,000 x 3,000 = 9,000,000 mesh "
                                    "vertices is too many: at most 4,000,000"),
    ("weight_bounds: [1.0e-300, 5]\n", "cfg.yaml: config key 'weight_bounds': 1e-300 is too small: at least 1e-06"),
    ("topology: " + "x" * 10_000 + "\n", "cfg.yaml: config key 'topology': expected one of open, cylinder, "
                                       "sphere, torus, auto, got 'xxxxxxxxxxxxxxxxx...xxxxxxxxxxxxxxxxxx'"),
])
def test_error_names_file_and_key(tmp_path, text, expected):
    assert error_of(tmp_path, text).startswith(expected)


def test_malformed_yaml_names_file_and_line(tmp_path):
    message = error_of(tmp_path, "orders: [3, 3\nnet_size: [5, 5]\n")
    assert message.startswith("malformed YAML in cfg.yaml: ")
    assert "line 2" in message


def test_duplicate_key_is_an_error(tmp_path):
    message = error_of(tmp_path, "orders: [3, 3]\norders: [4, 4]\n")
    assert "malformed YAML" in message and "duplicate key 'orders'" in message and "line 2" in message


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.yaml: config file not found$"):
        load_config(tmp_path / "nope.yaml")


def test_directory(tmp_path):
    with pytest.raises(ConfigError, match="is a directory"):
        load_config(tmp_path)


def test_not_utf8(tmp_path):
    path = tmp_path / "cfg.yaml"
    path.write_bytes(b"orders: [3, 3]\n\xff\xfe\n")
    with pytest.raises(ConfigError, match=r"cfg\.yaml: config file is not UTF-8 text"):
        load_config(path)


def test_trim_key_accepts_auto_true_false_only():
    from psonurbs.config import FitConfig, config_from_dict
    from psonurbs.errors import ConfigError

    assert FitConfig().trim == "auto"
    assert config_from_dict({"trim": True}).trim is True
    assert config_from_dict({"trim": False}).trim is False
    for bad in ("yes", 1, None):
        with pytest.raises(ConfigError, match="'trim': expected auto, true or false"):
            config_from_dict({"trim": bad})


@pytest.mark.parametrize("text, problem", [
    ("a0: &a0 [1, 2, 3, 4, 5, 6, 7, 8, 9]\n" + "".join(
        f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]\n" for i in range(1, 10)) + "tessellation: *a9\n",
     "more than 10,000 values once its aliases are expanded"),
    ("a: &a 1\nb: [" + ", ".join(["*a"] * 101) + "]\n", "more than 100 aliases"),
    ("tessellation: " + "[" * 40 + "]" * 40 + "\n", "nested deeper than 32 levels"),
    ("swarm:\n  particles: " + "9" * 5000 + "\n", "Exceeds the limit (4300 digits)"),
])
def test_yaml_that_would_expand_without_bound_is_refused(tmp_path, text, problem):
    message = error_of(tmp_path, text)
    assert message.startswith("malformed YAML in cfg.yaml: ") and problem in message
    assert len(message) < 400


def test_a_large_config_file_is_refused_unread(tmp_path):
    message = error_of(tmp_path, "# " + "x" * (1 << 20) + "\n")
    assert message == "cfg.yaml: file is too large (1 MiB; at most 1 MiB for a config file)"


def test_config_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "cfg.yaml"
    path.write_bytes(b"\xef\xbb\xbfswarm: {particles: 3}\n")
    assert load_config(path).swarm.particles == 3


# ---- the table of fields: defaults, validation and the rendered docs --------------

def test_the_table_has_one_row_per_key_in_the_dataclasses_order():
    from psonurbs.config import FIELDS

    keys = []  # (a config with a tolerance, of several faces, free edges, writes those keys too)
    for key, value in FitConfig(tolerance=1.0, patches="auto", align_edges=False).to_dict().items():
        keys += [f"swarm.{name}" for name in value] if key == "swarm" else [key]
    assert list(FIELDS) == keys


def test_the_dataclasses_defaults_are_the_tables():
    from psonurbs.config import FIELDS

    config = FitConfig()
    for key, row in FIELDS.items():
        owner = config.swarm if key.startswith("swarm.") else config
        assert getattr(owner, row.name) == row.default, key


def test_every_key_is_checked_by_its_row():
    from psonurbs.config import FIELDS

    for key, row in FIELDS.items():
        bad = "x" if row.kind == "number" else 0.5
        d = {"swarm": {row.name: bad}} if key.startswith("swarm.") else {key: [bad, bad] if row.pair else bad}
        with pytest.raises(ConfigError) as info:
            config_from_dict(d)
        assert str(info.value).startswith(f"config key '{key}': expected {row.expected()}, got "), key


# A value above its bound, and the keys that let the bound itself pass.
ABOVE_BOUND = {"orders": {"net_size": [12, 12]}, "swarm.particles": {"swarm": {"iterations": 1}},
               "swarm.iterations": {"swarm": {"particles": 1}}, "tessellation": {}}


def test_every_bound_of_the_table_is_enforced_and_named():
    from psonurbs.config import FIELDS

    for key, row in FIELDS.items():
        if row.most is None:
            continue
        at, above = row.most, row.most + 1
        if row.kind == "number" and key != "weight_bounds":
            above = row.most * 1.5
        extra = ABOVE_BOUND.get(key, {})

        def config(value, key=key, row=row, extra=extra):
            if key.startswith("swarm."):
                return config_from_dict({"swarm": {**extra.get("swarm", {}), row.name: value}})
            value = ([row.default[0], value] if key != "weight_bounds" else [0.5, value]) if row.pair else value
            return config_from_dict({**extra, key: value})

        config(at)  # the bound itself is allowed
        with pytest.raises(ConfigError) as info:
            config(above)
        assert f"config key '{key}': " in str(info.value) and f"is too large: at most {row.most:,} ({row.why})" \
            in str(info.value), key


def test_the_fit_commands_overriding_options_come_from_the_table():
    from psonurbs.cli.main import fit
    from psonurbs.config import FIELDS, option_help, yaml_text

    helps = {opt: getattr(param, "help", None) for param in fit.params for opt in param.opts}
    for key, row in FIELDS.items():
        if row.option:
            assert helps[row.option] == option_help(key) and f"default {yaml_text(row.default)}" in helps[row.option]
    assert {"--seed", "--particles", "--iterations", "--topology", "--strategy", "--parametrisation"} <= {
        row.option for row in FIELDS.values()}


def test_the_readme_holds_the_rendered_configuration_table():
    from psonurbs.config import README_END, README_START, render_readme_table

    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert README_START in readme and README_END in readme, \
        "README.md lacks the configuration table's marker lines"
    between = readme[readme.index(README_START) + len(README_START):readme.index(README_END)]
    assert between == "\n" + render_readme_table(), \
        "README.md's configuration table is stale: run python3 -m psonurbs.config --readme README.md"


def test_docs_configuration_is_as_rendered():
    from psonurbs.config import DOCS_PATH, render_configuration_doc

    assert (REPO / DOCS_PATH).read_text(encoding="utf-8") == render_configuration_doc(), \
        f"{DOCS_PATH} is stale: run python3 -m psonurbs.config --docs {DOCS_PATH}"


def test_the_rendered_table_has_a_row_per_key_and_alias():
    from psonurbs.config import ALIASES, FIELDS, render_readme_table

    rows = render_readme_table().splitlines()[2:]
    assert [row.split(" | ")[0].strip("| `") for row in rows] == [*FIELDS, *ALIASES]
    assert "| `swarm.particles` | integer | `40` | >= 1, <= 10,000;" in rows[4]
    assert "| `smoothing` | number | `1e-6` | >= 0, <= 1e6 |" in rows[10]


def test_the_module_regenerates_both_from_the_command_line(tmp_path):
    import subprocess
    import sys

    from psonurbs.config import README_END, README_START, render_configuration_doc, render_readme_table

    env_root = str(REPO)  # this checkout's psonurbs, as from a plain clone
    printed = subprocess.run([sys.executable, "-m", "psonurbs.config", "--readme"], capture_output=True, text=True,
                             cwd=tmp_path, env={"PYTHONPATH": env_root}, check=True).stdout
    assert printed == render_readme_table()
    readme = tmp_path / "README.md"
    readme.write_text(f"# x\n\n{README_START}\nold table\n{README_END}\nafter\n")
    subprocess.run([sys.executable, "-m", "psonurbs.config", "--readme", str(readme), "--docs",
                    str(tmp_path / "configuration.md")], cwd=tmp_path, env={"PYTHONPATH": env_root}, check=True)
    assert readme.read_text() == f"# x\n\n{README_START}\n{render_readme_table()}{README_END}\nafter\n"
    assert (tmp_path / "configuration.md").read_text() == render_configuration_doc()


def test_an_integer_beyond_the_float_range_is_a_config_error(tmp_path):
    """A 401-digit integer for a number key is refused as ``.inf`` is, not an overflow."""
    huge = error_of(tmp_path, "smoothing: 1" + "0" * 400 + "\n")
    assert huge.startswith("cfg.yaml: config key 'smoothing': expected a finite number >= 0, got 1000")
    assert "(401 digits)" in huge
    negative = error_of(tmp_path, "weight_bounds: [-1" + "0" * 400 + ", 5]\n")
    assert "config key 'weight_bounds': expected" in negative
