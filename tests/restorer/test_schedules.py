import pytest
import torch
from diffusers import CogVideoXDDIMScheduler

from tracegs.restorer.config import ScheduleConfig
from tracegs.restorer.schedules import RectifiedFlowSchedule, VPredictionDDIMSchedule


def schedules():
    return [
        RectifiedFlowSchedule(ScheduleConfig(kind="rectified_flow", deploy_steps=20)),
        RectifiedFlowSchedule(ScheduleConfig(kind="rectified_flow", deploy_steps=20, noise_scale=0.2)),
        VPredictionDDIMSchedule(ScheduleConfig(kind="vpred_ddim", deploy_steps=50)),
    ]


IDS = ["rectified_flow", "rectified_flow_small_noise", "vpred_ddim"]


@pytest.mark.parametrize("steps", [50, 10])
def test_ddim_step_matches_diffusers_cogvideox_scheduler(steps):
    ours = VPredictionDDIMSchedule(ScheduleConfig(kind="vpred_ddim", deploy_steps=steps))
    # CogVideoX-5B's scheduler_config.json values
    reference = CogVideoXDDIMScheduler(
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        clip_sample=False,
        prediction_type="v_prediction",
        rescale_betas_zero_snr=True,
        set_alpha_to_one=True,
        snr_shift_scale=1.0,
        timestep_spacing="trailing",
    )
    reference.set_timesteps(steps)
    grid = ours.timesteps(steps)
    assert torch.equal(grid[:-1], reference.timesteps)
    g = torch.Generator().manual_seed(0)
    z, v = torch.randn(2, 3, 4, 5, 6, generator=g), torch.randn(2, 3, 4, 5, 6, generator=g)
    for t, t_prev in zip(grid[:-1], grid[1:]):
        expected = reference.step(v, int(t), z).prev_sample
        got = ours.step(z, v, t.expand(2), t_prev.expand(2))
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
        noise = torch.randn(z.shape, generator=g)
        torch.testing.assert_close(
            ours.add_noise(z, noise, t.expand(2)),
            reference.add_noise(z, noise, t.expand(2)),
            rtol=1e-5,
            atol=1e-5,
        )
        torch.testing.assert_close(
            ours.velocity_target(z, noise, t.expand(2)),
            reference.get_velocity(z, noise, t.expand(2)),
            rtol=1e-5,
            atol=1e-5,
        )


@pytest.mark.parametrize("schedule", schedules(), ids=IDS)
def test_rollout_with_exact_velocity_recovers_clean_latent(schedule):
    g = torch.Generator().manual_seed(1)
    x0, noise = torch.randn(2, 3, 4, 6, 6, generator=g), torch.randn(2, 3, 4, 6, 6, generator=g)
    for grid in (schedule.timesteps(), schedule.resample(schedule.timesteps(), 5, g)):
        z = schedule.add_noise(x0, noise, grid[0].expand(2))
        assert not torch.allclose(z, x0, atol=0.1)
        for t, t_prev in zip(grid[:-1], grid[1:]):
            z = schedule.step(
                z, schedule.velocity_target(x0, noise, t.expand(2)), t.expand(2), t_prev.expand(2)
            )
        torch.testing.assert_close(z, x0, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("schedule", schedules(), ids=IDS)
def test_predict_clean_inverts_add_noise(schedule):
    g = torch.Generator().manual_seed(2)
    x0, noise = torch.randn(4, 2, 3, 4, 4, generator=g), torch.randn(4, 2, 3, 4, 4, generator=g)
    t = schedule.sample_train_t(4, g)
    z = schedule.add_noise(x0, noise, t)
    torch.testing.assert_close(
        schedule.predict_clean(z, schedule.velocity_target(x0, noise, t), t), x0, atol=1e-4, rtol=1e-4
    )


@pytest.mark.parametrize("schedule", schedules(), ids=IDS)
def test_velocity_toward_a_clean_frame_predicts_that_frame(schedule):
    """The velocity Stage 2 compares the student with under loss.trajectory_target=pseudo_target: at any state
    above the clean end, its clean prediction is the given frame."""
    g = torch.Generator().manual_seed(1)
    z, x0 = torch.randn(2, 3, 4, 5, 6, generator=g), torch.randn(2, 3, 4, 5, 6, generator=g)
    t = schedule.timesteps()[:-1][torch.tensor([0, 7])]
    torch.testing.assert_close(schedule.predict_clean(z, schedule.velocity_toward(z, x0, t), t), x0,
                               rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("schedule", schedules(), ids=IDS)
def test_resampled_grid_is_strictly_decreasing_subset_with_both_ends(schedule):
    grid = schedule.timesteps()
    assert (grid[1:] < grid[:-1]).all()
    g = torch.Generator().manual_seed(3)
    seen = set()
    for n in (1, 2, 5, 10, grid.numel() - 1):
        for _ in range(5):
            sub = schedule.resample(grid, n, g)
            assert sub.numel() == n + 1
            assert sub[0] == grid[0] and sub[-1] == grid[-1]
            assert (sub[1:] < sub[:-1]).all()
            assert all(bool((grid == value).any()) for value in sub)
            seen.add(tuple(sub.tolist()))
    assert len(seen) > 5  # interior points are actually resampled
    with pytest.raises(ValueError, match="rollout steps"):
        schedule.resample(grid, grid.numel(), g)


def test_deployment_schedule_ends():
    rf, _, ddim = schedules()
    assert rf.timesteps(20)[0] == 1.0 and rf.timesteps(20)[-1] == 0.0 and rf.timesteps(20).numel() == 21
    grid = ddim.timesteps(50)
    assert grid.numel() == 51 and grid[0] == 999 and grid[-1] == -1
    # zero terminal SNR: the first point is pure noise
    assert float(ddim.alpha_bar(grid[:1])) == pytest.approx(0.0, abs=1e-8)


def test_training_times_follow_the_configured_power_law():
    """train_time_power p draws t with density (p + 1) t^p: P(t > 1/2) = 1 - 2^-(p+1); p = 0 is uniform."""
    draws = {p: RectifiedFlowSchedule(ScheduleConfig(train_time_power=p)).sample_train_t(
        8192, torch.Generator().manual_seed(0)) for p in (0.0, 6.0)}
    assert float((draws[0.0] > 0.5).float().mean()) == pytest.approx(0.5, abs=0.02)
    assert float((draws[6.0] > 0.5).float().mean()) == pytest.approx(1 - 2**-7, abs=0.01)
    assert float(draws[6.0].min()) >= 0.0 and float(draws[6.0].max()) <= 1.0
    # the deployment grid does not depend on it
    assert torch.equal(RectifiedFlowSchedule(ScheduleConfig(train_time_power=6.0)).timesteps(4),
                       torch.linspace(1.0, 0.0, 5))


def test_deployment_grid_follows_its_own_power_law():
    """deploy_time_power q puts the M + 1 points at equal steps of t^(q + 1), the CDF of the training density with
    p = q: each solver step then spans an equal share of the training times, and the last state the solver
    visits before the clean end lies where a t^12 training density still draws."""
    grid = RectifiedFlowSchedule(ScheduleConfig(deploy_time_power=12.0)).timesteps(20)
    assert grid[0] == 1.0 and grid[-1] == 0.0 and bool((grid.diff() < 0).all())
    assert torch.allclose(grid**13, torch.linspace(1.0, 0.0, 21), atol=1e-6)
    assert float(grid[-2]) == pytest.approx(0.05 ** (1 / 13), abs=1e-6)  # 0.794; the uniform grid's is 0.05
    assert torch.equal(RectifiedFlowSchedule(ScheduleConfig()).timesteps(20), torch.linspace(1.0, 0.0, 21))


def test_training_times_can_be_logit_normal():
    """train_time_logit_normal [m, s]: t = sigmoid(m + s n), n ~ N(0, 1) (Esser et al. 2024): median sigmoid(m),
    every draw inside (0, 1), and it takes the place of the power law."""
    cfg = ScheduleConfig(train_time_power=6.0, train_time_logit_normal=[1.0, 1.2])
    t = RectifiedFlowSchedule(cfg).sample_train_t(8192, torch.Generator().manual_seed(0))
    assert float(t.median()) == pytest.approx(torch.sigmoid(torch.tensor(1.0)).item(), abs=0.01)
    assert float(t.min()) > 0.0 and float(t.max()) < 1.0
    logits = torch.logit(t.double())
    assert float(logits.std()) == pytest.approx(1.2, abs=0.03)


def test_a_uniform_share_of_training_times_reaches_the_low_noise_states():
    """train_time_uniform_share mixes uniform draws into a density concentrated near t = 1: with t^12 and a
    quarter uniform, P(t < 0.5) = 0.25 * 0.5 + 0.75 * 0.5^13; without a share the draws are t^12's own."""
    power = ScheduleConfig(kind="rectified_flow", train_time_power=12)
    mixed = RectifiedFlowSchedule(ScheduleConfig(kind="rectified_flow", train_time_power=12,
                                                 train_time_uniform_share=0.25))
    t = mixed.sample_train_t(200_000, torch.Generator().manual_seed(0))
    assert float((t < 0.5).float().mean()) == pytest.approx(0.25 * 0.5 + 0.75 * 0.5**13, abs=0.005)
    assert 0.0 <= float(t.min()) and float(t.max()) <= 1.0
    plain = RectifiedFlowSchedule(power).sample_train_t(1000, torch.Generator().manual_seed(3))
    assert torch.equal(plain, torch.rand(1000, generator=torch.Generator().manual_seed(3)) ** (1 / 13))


def test_a_trajectory_starts_at_the_noise_end_of_the_training_path():
    """The sampler's first state ``prior(eps)`` is the forward path at the grid's first time: sigma_n eps for a
    rectified flow with noise end sigma_n (x0 has no weight at t = 1), CogVideoX's pure noise for DDIM."""
    g = torch.Generator().manual_seed(4)
    x0, noise = torch.randn(2, 3, 4, 4, 4, generator=g), torch.randn(2, 3, 4, 4, 4, generator=g)
    standard, small, ddim = schedules()
    for schedule in (small, standard):
        start = schedule.timesteps()[0].expand(2)
        torch.testing.assert_close(schedule.prior(noise), schedule.add_noise(x0, noise, start))
    torch.testing.assert_close(small.prior(noise), 0.2 * noise)
    assert torch.equal(ddim.prior(noise), noise)
