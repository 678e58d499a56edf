"""TOML -> typed dataclass loading: unknown keys, wrong types, ranges are rejected with the
file, key and value in the message."""

import tomllib
from dataclasses import dataclass, field

import pytest

from handfe.config import bounds, choices, from_dict, load, toml_string
from handfe.errors import ConfigError


@dataclass(frozen=True)
class Plate:
    angle_deg: float = field(default=15.0, metadata=bounds(0.0, 90.0))
    mode: str = field(default="force", metadata=choices("force", "displacement"))


@dataclass(frozen=True)
class Scene:
    name: str
    plate: Plate = field(default_factory=Plate)
    levels: tuple[float, ...] = (5.0, 10.0)
    steps: int = field(default=4, metadata=bounds(1, None))


def test_roundtrip(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('name = "pinch"\nsteps = 3\nlevels = [5, 20]\n[plate]\nangle_deg = 30\n')
    s = load(Scene, f)
    assert s == Scene("pinch", Plate(30.0, "force"), (5.0, 20.0), 3)


@pytest.mark.parametrize("text,needle", [
    ('name = "a"\ncolour = 1\n', "unknown key 'colour'"),
    ('name = "a"\n[plate]\nangel_deg = 3\n', "unknown key 'plate.angel_deg'"),
    ('name = "a"\n[plate]\nangle_deg = 120\n', "'plate.angle_deg' = 120"),
    ('name = "a"\n[plate]\nmode = "velocity"\n', "must be one of force, displacement"),
    ('name = "a"\nsteps = 0\n', "out of range"),
    ('name = "a"\nsteps = 1.5\n', "expected an integer"),
    ("steps = 2\n", "missing required key 'name'"),
    ('name = "a"\nlevels = "x"\n', "expected a list"),
    ("name = \n", "not valid TOML"),
])
def test_rejections_name_file_key_value(tmp_path, text, needle):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as ei:
        load(Scene, f)
    assert needle in str(ei.value) and str(f) in str(ei.value)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load(Scene, tmp_path / "nope.toml")


def test_from_dict_source_label():
    with pytest.raises(ConfigError, match="<cli>: unknown key 'x'"):
        from_dict(Scene, {"name": "a", "x": 1}, source="<cli>")


@pytest.mark.parametrize("text", ['plain', 'a "quoted" pose', "back\\slash", "two\nlines\ttab",
                                  "caf\u00e9 \u00b5m", "ctrl\x01", ""])
def test_toml_string_reads_back(text):
    assert tomllib.loads(f"k = {toml_string(text)}")["k"] == text
