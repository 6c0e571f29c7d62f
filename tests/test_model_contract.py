"""The model contract: one typed record of what a model promises the robot, validated once, written once."""

import dataclasses

import pytest

from dssp_core.errors import ConfigError
from dssp_data.model_contract import CONTRACT_FIELDS, ModelContract, check_chunk
from dssp_data.observation import ObservationContract, PointCloudConfig, piper_layout
from dssp_train.config import apply_overrides, load_preset


def contract(**changes) -> ModelContract:
    return dataclasses.replace(ModelContract(), **changes)


@pytest.mark.parametrize(
    "n, h, ha, offset, words",
    [
        (2, 4, 5, 0, "contract.n_action_steps (H_a) must be in [1, horizon=4], got 5"),
        (3, 8, 7, 2, "contract.n_action_steps (H_a) must be at most horizon - N + 1 = 6, got 7: DP3's alignment"),
        (3, 8, 2, 1, "contract.action_offset must be 0 or n_obs_steps - 1 = 2, got 1"),
    ],
)
def test_the_executed_slice_must_lie_in_the_chunk(n, h, ha, offset, words):
    with pytest.raises(ConfigError) as err:
        check_chunk(n, h, ha, offset, "contract")
    assert str(err.value).startswith(words)
    with pytest.raises(ConfigError, match="n_action_steps|action_offset"):
        contract(n_obs_steps=n, horizon=h, n_action_steps=ha, action_offset=offset)
    start = offset if offset in (0, n - 1) else n - 1
    check_chunk(n, h, h - start, start, "contract")  # the largest H_a that fits


def test_the_training_config_checks_the_chunk_with_the_same_rule():
    with pytest.raises(
        ConfigError, match=r"^--set model.n_action_steps=9: model.n_action_steps \(H_a\) must be in \[1, horizon="
    ):
        apply_overrides(load_preset("tiny"), ["model.n_action_steps=9"])


def test_the_sampler_runs_from_noise_to_data_and_k_is_its_length():
    assert contract(ddim_timesteps=[99, 49]).denoise_steps == 2
    for steps in ([0, 10], [5, 5], []):
        with pytest.raises(ConfigError, match="ddim_timesteps"):
            contract(ddim_timesteps=steps)


def test_the_observation_contract_must_fit_the_dimensions():
    fits = ObservationContract(pointcloud=PointCloudConfig(n_points=64), state=piper_layout(1), action=piper_layout(1))
    assert contract(observation=fits).observation == fits
    with pytest.raises(ConfigError, match="contract.observation.state makes 7 values but the model takes 14"):
        contract(state_dim=14, action_dim=14, observation=fits)
    with pytest.raises(ConfigError, match="pointcloud.n_points makes 64 values but the model takes 128"):
        contract(n_points=128, observation=fits)


def test_json_round_trip_every_field_required_and_the_digest_follows_the_facts():
    c = contract(control_rate_hz=10.0, observation=ObservationContract(state=piper_layout(1)))
    data = c.to_json()
    assert data["observation"]["pointcloud"] == "unknown" and ModelContract.from_json(data) == c
    for name in ("n_action_steps", "control_rate_hz", "observation"):
        with pytest.raises(ConfigError, match=f"^contract.{name} is missing$"):
            ModelContract.from_json({k: v for k, v in data.items() if k != name})
    assert c.digest() == ModelContract.from_json(data).digest()
    assert len({c.digest(), contract(control_rate_hz=20.0).digest(), contract(n_action_steps=2).digest()}) == 3


@pytest.mark.parametrize("alignment", ["current", "dp3"])
def test_the_run_builds_the_contract_and_model_config_keeps_the_rest(alignment):
    from export.manifest_writer import architecture

    config = apply_overrides(
        load_preset("tiny"),
        [f"model.action_alignment={alignment}", "model.state_dim=7", "model.action_dim=7", "control_rate_hz=50"],
    )
    c = config.contract([90, 45, 0], inpainting=True)
    m = config.model
    assert (c.n_obs_steps, c.horizon, c.n_action_steps, c.action_offset) == (
        m.n_obs_steps,
        m.horizon,
        m.n_action_steps,
        m.action_offset,
    )
    assert c.control_rate_hz == 50.0 and c.inpainting and c.denoise_steps == 3 and c.observation == config.observation
    kept = architecture(m)
    assert not set(kept) & set(CONTRACT_FIELDS)  # each fact once
    assert {**kept, **c.model_fields()} == dataclasses.asdict(m)  # nothing lost
