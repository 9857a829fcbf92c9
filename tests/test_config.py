"""Config: defaults, TOML files, overrides, validation messages and the written-out resolved config."""

import dataclasses

import pytest

from romannet.common.config import Config, ExplorationConfig, RewardConfig, WorkspaceConfig, load_config
from romannet.common.configbase import dumps_toml, to_dict, write_toml
from romannet.common.errors import ConfigError


def test_defaults_match_the_paper():
    cfg = load_config()
    assert (cfg.workspace.height_px, cfg.workspace.width_px) == (224, 224)
    assert cfg.reward.weight("push") == 0.2 and cfg.reward.weight("pick") == 1.0 and cfg.reward.weight("place") == 1.0
    assert cfg.reward.anisotropy == 2.0
    assert (cfg.exploration.alpha, cfg.exploration.sigma, cfg.exploration.beta) == (0.5, 0.33, 0.25)
    assert cfg.exploration.initial_rate == 0.5
    assert cfg.camera.intrinsics[0][0] == pytest.approx(618.62)


def test_no_config_trains_the_clutter_recipe():
    """`romannet up` without --config trains what `make run` does (configs/experiments/clutter.toml): the
    defaults are that recipe, its pacing and two-harmonic pick head included."""
    from pathlib import Path
    recipe = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "clutter.toml"
    assert load_config() == load_config(recipe, ['run_id="default"'])
    cfg = load_config()
    assert cfg.replay.samples_per_insert == 4.0 and cfg.actor.spool_max_items == 2
    assert cfg.model.rotation_harmonics == 2


def test_toml_file_then_overrides(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text('run_id = "exp1"\n[reward]\npush_weight = 0.5\n[task]\nkind = "stacking"\n')
    cfg = load_config(path, ["reward.push_weight=0.3", "task.goal_stack_height=5"])
    assert cfg.run_id == "exp1"
    assert cfg.reward.push_weight == 0.3  # the override wins over the file
    assert cfg.task.kind == "stacking" and cfg.task.goal_stack_height == 5
    assert cfg.task.primitives == ("push", "pick", "place")


def test_written_config_reloads_identically(tmp_path):
    cfg = load_config(overrides=["seed=7", "model.precision=fp32", "exploration.policy=epsilon_greedy"])
    out = write_toml(cfg, tmp_path / "resolved" / "config.toml")
    assert load_config(out) == cfg
    assert "[exploration]" in dumps_toml(cfg)


@pytest.mark.parametrize(
    ("override", "field", "fragment"),
    [
        ("exploration.beta=1.5", "exploration.beta", "[0, 1)"),
        ("reward.anisotropy=0.5", "reward.anisotropy", "sigma_x / sigma_y"),
        ("reward.kernel_normalization=gauss", "reward.kernel_normalization", "'peak', 'paper'"),
        ("task.goal_stack_height=7", "task.goal_stack_height", "2..5"),
        ("model.channels=2.5", "model.channels", "integer"),
        ("reward.push_weight=true", "reward.push_weight", "number"),
        ("reward.no_such_field=1", "reward.no_such_field", "unknown field"),
        ("workspace.resolution_m=0.003", "workspace.x_max_m", "multiple of 4"),
        ("run_id=bad/id", "run_id", "letters, digits"),
        ("reward.sigma_y_px=nan", "reward.sigma_y_px", "finite"),
    ],
)
def test_bad_values_name_field_value_and_allowed(override, field, fragment):
    with pytest.raises(ConfigError) as info:
        load_config(overrides=[override])
    assert info.value.field == field
    assert fragment in str(info.value)
    assert field in str(info.value)


def test_configs_are_frozen():
    cfg = Config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seed = 3  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.reward.push_weight = 1.0  # type: ignore[misc]


def test_direct_construction_validates():
    with pytest.raises(ConfigError, match="exploration.top_k"):
        ExplorationConfig(top_k=0)
    with pytest.raises(ConfigError, match="workspace.x_max_m"):
        WorkspaceConfig(x_min_m=1.0, x_max_m=0.5)
    assert RewardConfig(kernel_normalization="paper").kernel_normalization == "paper"


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[reward\npush_weight = ")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="section.field=value"):
        load_config(overrides=["reward.push_weight"])


def test_every_experiment_recipe_loads():
    """The recipes in configs/experiments/ (the commands in README and docs/results.md name them)."""
    from pathlib import Path
    recipes = sorted((Path(__file__).resolve().parents[1] / "configs" / "experiments").glob("*.toml"))
    assert len(recipes) >= 7
    for path in recipes:
        cfg = load_config(path)
        assert cfg.replay.spi_limit is not None and cfg.actor.spool_max_items == 2, path  # paced
        # the stacking recipes, the paper's method and the clutter variants that measure it train two
        # transitions per action, as measured
        two = cfg.task.kind == "stacking" or path.stem == "clutter-paper" or path.stem.startswith("clutter-spi2")
        expected_spi = 2.0 if two else 4.0
        assert cfg.replay.samples_per_insert == expected_spi, path
        assert cfg.learner.publish_every_updates == 1, path  # the actor acts on the newest net
        if cfg.exploration.policy == "lae" and not path.stem.endswith("-paper"):  # -paper: as written, unfloored
            assert cfg.exploration.lae_min_rate == 0.1, path


def _flat_config(path) -> dict:
    def flat(d: dict, prefix: str = "") -> dict:
        out: dict = {}
        for key, value in d.items():
            out.update(flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
        return out

    return flat(to_dict(load_config(path)))


def test_ablation_recipes_differ_from_the_full_method_only_in_what_they_ablate():
    """An ablation compares one change: every other setting (schedule, loss, model) must be the full recipe's,
    or its curve measures something else too. lae_min_rate only acts under LAE, so it is left out."""
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "configs" / "experiments"
    exploration = {"exploration.policy": "epsilon_greedy"}
    x_only = {"reward.use_progress": False, "reward.use_gaussian": False}
    ablations = {
        ("clutter", "clutter-baseline"): {**x_only, **exploration},
        ("clutter", "clutter-tpg"): exploration,
        ("stacking", "stacking-baseline"): {**x_only, **exploration},
        ("stacking", "stacking-tpg"): exploration,
        ("stacking", "stacking-tp"): {"reward.use_gaussian": False},
        ("stacking", "stacking-paper-norm"): {"reward.kernel_normalization": "paper"},
        ("stacking", "stacking-pixel-lt"): {"reward.zero_reward_support": "pixel",
                                            "learner.executed_pixel_weight": 1.0},
    }
    for (full_name, name), changed in ablations.items():
        full, ablation = _flat_config(root / f"{full_name}.toml"), _flat_config(root / f"{name}.toml")
        differs = {k for k in full if full[k] != ablation[k]} - {"run_id", "exploration.lae_min_rate"}
        assert differs == set(changed), (name, differs ^ set(changed))
        assert all(ablation[k] == v for k, v in changed.items()), name
        assert full["exploration.policy"] == "lae" and full["reward.use_progress"] and full["reward.use_gaussian"]


def test_a_recipe_states_what_differs_from_its_base(tmp_path):
    """`base = "other.toml"` (relative to the recipe) is read first and the recipe's values laid over it,
    section by section; a chain of bases works, a loop or a missing base is one clear error."""
    (tmp_path / "full.toml").write_text('run_id = "full"\n[reward]\npush_weight = 0.25\nuse_gaussian = false\n'
                                        '[learner]\nlr = 0.001\n')
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "mid.toml").write_text('base = "../full.toml"\nrun_id = "mid"\n[reward]\npush_weight = 0.5\n')
    (tmp_path / "sub" / "top.toml").write_text('base = "mid.toml"\n[learner]\nlr = 0.002\n')
    cfg = load_config(tmp_path / "sub" / "top.toml", ["reward.use_gaussian=true"])
    assert cfg.run_id == "mid" and cfg.reward.push_weight == 0.5 and cfg.learner.lr == 0.002
    assert cfg.reward.use_gaussian  # the command line's --set still comes last
    (tmp_path / "a.toml").write_text('base = "b.toml"\n')
    (tmp_path / "b.toml").write_text('base = "a.toml"\n')
    with pytest.raises(ConfigError, match="loop"):
        load_config(tmp_path / "a.toml")
    (tmp_path / "c.toml").write_text('base = "nowhere.toml"\n')
    with pytest.raises(ConfigError, match="nowhere.toml"):
        load_config(tmp_path / "c.toml")


def test_an_unknown_field_names_the_near_miss():
    with pytest.raises(ConfigError, match=r"did you mean sim\.hand\?"):
        load_config(overrides=['sim.hands="rg2"'])
    with pytest.raises(ConfigError, match=r"did you mean learner\?"):
        load_config(overrides=["learnr.lr=0.1"])
    with pytest.raises(ConfigError, match=r"\[sim\] has: .*hand"):  # nothing close: the section's fields
        load_config(overrides=["sim.zzz=1"])


def _other_than(value: object) -> str:
    """An override value (TOML text) other than a retired field's kept value."""
    if isinstance(value, bool):
        return str(not value).lower()
    if isinstance(value, str):
        return f'"{value}-other"'
    return str(value + 1)  # type: ignore[operator]


def test_a_saved_config_naming_a_removed_field_loads_at_its_old_default():
    """Runs, checkpoints, model packages and MCAP episodes saved every field; a field since removed
    (common/config.py RETIRED) is dropped at the value that kept its code path off, anything else is one clear
    error naming the field."""
    from pathlib import Path

    import tomli_w

    from romannet.common.config import RETIRED, load_config_text, without_retired
    saved = dumps_toml(Config())
    for key, kept in RETIRED.items():
        section, name = key.split(".")
        assert f"[{section}]\n" in saved, key
        line = tomli_w.dumps({name: kept})
        assert load_config_text(saved.replace(f"[{section}]\n", f"[{section}]\n{line}", 1)) == Config()
        with pytest.raises(ConfigError, match=rf"'{key}' = .*this option was removed"):
            load_config(overrides=[f"{key}={_other_than(kept)}"])
    assert without_retired({"model": {"channels": 32, "dropout": 0.0}}) == {"model": {"channels": 32}}
    for package in sorted((Path(__file__).resolve().parents[1] / "models").glob("*/config.toml")):
        load_config(package)  # written before some fields were removed


def test_a_saved_config_without_a_field_whose_default_changed_loads_as_it_ran(tmp_path):
    """A config saved before model.rotation_harmonics existed ran the one-harmonic head, and one saved with no
    samples_per_insert ran without a ratio limit (its unset value was not written): a saved config (a run's,
    a checkpoint's, a package's) loads as it ran, a recipe that leaves them out gets the defaults."""
    from pathlib import Path

    import tomli_w

    from romannet.common.config import SAVED_WITHOUT, as_saved, load_config_text, load_saved_config
    assert set(SAVED_WITHOUT) == {"model.rotation_harmonics", "replay.samples_per_insert", "sim.coupled_fingers",
                                  "exploration.pick_clearance", "exploration.pick_angle", "model.pick_angle_bins",
                                  "exploration.pick_centre"}
    old = to_dict(Config())
    del old["model"]["rotation_harmonics"], old["replay"]["samples_per_insert"], old["sim"]["coupled_fingers"]
    del old["exploration"]["pick_clearance"], old["exploration"]["pick_angle"], old["model"]["pick_angle_bins"]
    del old["exploration"]["pick_centre"]
    path = tmp_path / "config.toml"
    path.write_text(tomli_w.dumps(old))
    for cfg in (load_saved_config(path), load_config_text(path.read_text())):
        assert cfg.model.rotation_harmonics == 1 and cfg.replay.spi_limit is None and not cfg.sim.coupled_fingers
        assert not cfg.exploration.pick_clearance
        assert cfg.exploration.pick_angle == "net" and cfg.model.pick_angle_bins == 0
        assert not cfg.exploration.pick_centre
    assert load_saved_config(path, ["model.rotation_harmonics=2"]).model.rotation_harmonics == 2
    assert load_config(path) == Config()  # a recipe: the defaults
    assert as_saved({"model": {"channels": 32}})["model"] == {"channels": 32, "rotation_harmonics": 1,
                                                              "pick_angle_bins": 0}
    write_toml(Config(), path)  # saved now: every field written, nothing filled in
    assert load_saved_config(path) == Config() == load_config_text(path.read_text())
    for package in sorted((Path(__file__).resolve().parents[1] / "models").glob("*/config.toml")):
        assert load_saved_config(package) == load_config(package)
