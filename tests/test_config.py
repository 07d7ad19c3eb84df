import subprocess
import sys

import pytest

from common.config import ConfigError, load_config


def test_defaults_carry_the_papers_values():
    cfg = load_config()
    assert cfg.vehicle.mass_kg == 1650.0
    assert (cfg.vehicle.pacejka_b, cfg.vehicle.pacejka_c, cfg.vehicle.pacejka_d,
            cfg.vehicle.pacejka_e) == (6.0, 2.5, 0.37, 1.1)
    assert cfg.planner.horizon == 40 and cfg.planner.dt_s == 0.1
    assert cfg.sensor.hfov_deg == 72.0 and cfg.sensor.range_m == 25.0
    assert cfg.mapper.size_cells * cfg.mapper.resolution_m == pytest.approx(80.0)
    assert cfg.mapper.prior_variance == 3.0
    assert cfg.plant.rate_hz == 50.0


def test_overrides_and_file(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[planner]\nsamples = 123\n")
    cfg = load_config(f, ["episode.seed=7", "episode.scenario=alleyway"])
    assert cfg.planner.samples == 123 and cfg.episode.seed == 7
    assert cfg.episode.scenario == "alleyway"
    assert cfg.replace(**{"planner.samples": 9}).planner.samples == 9


@pytest.mark.parametrize("override, names", [
    ("planner.samples=-5", "planner.samples"),
    ("planner.samples=1.5", "planner.samples"),
    ("planner.temperature=0", "planner.temperature"),
    ("episode.clock=fast", "episode.clock"),
    ("episode.scenario=moon", "episode.scenario"),
    ("planner.nonsense=1", "planner.nonsense"),
    ("nosection.x=1", "nosection"),
    ("bus.multicast_scouting=3", "bus.multicast_scouting"),
    ("vehicle.mass_kg=nan", "vehicle.mass_kg"),
    ("planner.dt_s=0.013", "planner.dt_s"),
    ('bus.mode="peer"', "bus.mode=peer"),
])
def test_bad_values_name_the_key(override, names):
    with pytest.raises(ConfigError, match=names.replace(".", r"\.")):
        load_config(overrides=[override])


def test_bad_file_is_a_clear_error(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text("[planner\nsamples=")
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config(f)


def test_cli_rejects_bad_config_before_starting():
    r = subprocess.run([sys.executable, "-m", "deploy", "up", "--samples", "0"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "planner.samples" in r.stderr


def test_parameters_doc_is_generated_from_the_defaults():
    from pathlib import Path

    from common.config import default_dict, parameters_markdown
    doc = Path(__file__).resolve().parents[1] / "docs" / "parameters.md"
    assert doc.read_text() == parameters_markdown(), \
        "regenerate: vamppi config --markdown > docs/parameters.md"
    for section, values in default_dict().items():
        for key in values:
            assert f"| `{key}` |" in doc.read_text(), f"{section}.{key}"


def test_params_are_built_by_name_and_a_misnamed_field_is_an_error():
    from dataclasses import dataclass

    from common.config import by_name

    @dataclass(frozen=True)
    class P:
        samples: int           # planner.samples
        hfov_deg: float        # sensor.hfov_deg
        twice: int             # derived

    cfg = load_config(overrides=["planner.samples=7", "sensor.hfov_deg=60.0"])
    assert by_name(P, cfg.planner, cfg.sensor, twice=14) == P(7, 60.0, 14)
    with pytest.raises(TypeError, match="no config key and no value for twice"):
        by_name(P, cfg.planner, cfg.sensor)
    with pytest.raises(TypeError, match="has no field thrice"):
        by_name(P, cfg.planner, cfg.sensor, twice=14, thrice=21)

    @dataclass(frozen=True)
    class Q:
        sample: int            # a typo for planner.samples: no such key
    with pytest.raises(TypeError, match="no config key and no value for sample"):
        by_name(Q, cfg.planner)
