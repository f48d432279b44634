"""Noise schedules behind one interface (main paper Eq. 1 solver T_i, Eq. 4 rollout, Alg. 1 Resample).

Both schedules use the velocity parameterisation the restorer predicts:
- ``RectifiedFlowSchedule`` (tiny backbone): z_t = (1 - t) x0 + t sigma_n eps, v = sigma_n eps - x0, t in [0, 1],
  Euler steps (sigma_n = ``noise_scale``, 1 on the standard path).
- ``VPredictionDDIMSchedule`` (CogVideoX): z_t = sqrt(a_t) x0 + sqrt(1 - a_t) eps, v = sqrt(a_t) eps - sqrt(1 - a_t) x0
  with integer DDPM steps t in [0, T-1] and deterministic DDIM updates; the clean end of a grid is t = -1
  (alpha-bar = 1, diffusers' ``set_alpha_to_one``). This is what the paper calls velocity / flow matching.

Time grids always run from pure noise (first) to the clean end (last), strictly decreasing.
"""

from __future__ import annotations

import torch

from tracegs.restorer.config import ScheduleConfig


def _expand(values: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Broadcast a per-sample ``(B,)`` (or scalar) tensor over the trailing latent dims of ``like``."""
    values = values.to(device=like.device, dtype=like.dtype).reshape(-1)
    return values.reshape(-1, *([1] * (like.dim() - 1)))


class NoiseSchedule:
    """Interface shared by the schedules; subclasses implement the coefficient maps."""

    def __init__(self, cfg: ScheduleConfig):
        self.cfg = cfg

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def velocity_target(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def predict_clean(self, z: torch.Tensor, v: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def velocity_toward(self, z: torch.Tensor, x0: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The velocity whose clean prediction at state ``z`` is ``x0`` (``predict_clean`` inverted; t above the
        clean end)."""
        raise NotImplementedError

    def step(self, z: torch.Tensor, v: torch.Tensor, t: torch.Tensor, t_prev: torch.Tensor) -> torch.Tensor:
        """Solver step T_i from t to t_prev < t (main paper Eq. 1), deterministic."""
        raise NotImplementedError

    def timesteps(self, steps: int | None = None) -> torch.Tensor:
        """The M-step deployment schedule: ``M + 1`` strictly decreasing points, pure noise first, clean last."""
        raise NotImplementedError

    def prior(self, noise: torch.Tensor) -> torch.Tensor:
        """The first state of every trajectory, z at the grid's noise end, from standard normal ``noise``."""
        return noise

    def sample_train_t(self, batch: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Per-sample training times for forward-noised states (Stage 1, baseline, off-policy)."""
        raise NotImplementedError

    def resample(self, grid: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Stage-2 training grid {t'_i}, i = 0..N (Alg. 1 Resample): ``n + 1`` points of ``grid``.

        Keeps the first (pure noise) and last (clean) points and draws ``n - 1`` distinct interior points
        uniformly without replacement, so the rollout always starts from noise and ends clean.
        """
        m = grid.numel() - 1
        if not 1 <= n <= m:
            raise ValueError(f"rollout steps N={n} must be in [1, M={m}] of the deployment grid")
        interior = torch.randperm(m - 1, generator=generator)[: n - 1] + 1
        keep = torch.cat([torch.tensor([0]), interior.sort().values, torch.tensor([m])])
        return grid[keep]


class RectifiedFlowSchedule(NoiseSchedule):
    """z_t = (1 - t) x0 + t sigma_n eps with sigma_n = ``noise_scale`` (1: the standard path)."""

    def add_noise(self, x0, noise, t):
        t = _expand(t, x0)
        return (1.0 - t) * x0 + t * self.cfg.noise_scale * noise

    def velocity_target(self, x0, noise, t):
        return self.cfg.noise_scale * noise - x0

    def prior(self, noise):
        return self.cfg.noise_scale * noise

    def predict_clean(self, z, v, t):
        return z - _expand(t, z) * v

    def velocity_toward(self, z, x0, t):
        return (z - x0) / _expand(t, z)

    def step(self, z, v, t, t_prev):
        return z + (_expand(t_prev, z) - _expand(t, z)) * v

    def timesteps(self, steps=None):
        m = steps or self.cfg.deploy_steps
        return torch.linspace(1.0, 0.0, m + 1) ** (1.0 / (1.0 + self.cfg.deploy_time_power))

    def sample_train_t(self, batch, generator=None):
        if self.cfg.train_time_logit_normal is not None:
            mean, std = self.cfg.train_time_logit_normal
            t = torch.sigmoid(mean + std * torch.randn(batch, generator=generator))
        else:
            # Density (p + 1) t^p on [0, 1] by inverse CDF (p = train_time_power; 0 = uniform).
            t = torch.rand(batch, generator=generator) ** (1.0 / (1.0 + self.cfg.train_time_power))
        if self.cfg.train_time_uniform_share == 0.0:
            return t  # the generator's stream of a design without the mixture stays as it was
        uniform = torch.rand(batch, generator=generator) < self.cfg.train_time_uniform_share
        return torch.where(uniform, torch.rand(batch, generator=generator), t)


class VPredictionDDIMSchedule(NoiseSchedule):
    """CogVideoX's v-prediction DDPM with deterministic DDIM (eta = 0) steps.

    The cumulative alphas come from diffusers' ``CogVideoXDDIMScheduler`` (scaled-linear betas, SNR shift,
    zero-terminal-SNR rescale), so training noise matches the pretrained model. The step is written out
    because diffusers' ``step`` fixes the previous timestep to ``t - T // M``; Stage 2's resampled grids
    need arbitrary ``t_prev``. On the uniform grid the two coincide (tested).
    """

    def __init__(self, cfg: ScheduleConfig):
        from diffusers import CogVideoXDDIMScheduler

        super().__init__(cfg)
        self.scheduler = CogVideoXDDIMScheduler(
            num_train_timesteps=cfg.num_train_timesteps,
            beta_start=cfg.beta_start,
            beta_end=cfg.beta_end,
            beta_schedule=cfg.beta_schedule,
            clip_sample=False,
            set_alpha_to_one=True,
            prediction_type="v_prediction",
            timestep_spacing="trailing",
            rescale_betas_zero_snr=cfg.rescale_betas_zero_snr,
            snr_shift_scale=cfg.snr_shift_scale,
        )
        # Index 0 holds the clean end t = -1 (alpha-bar 1); index k + 1 holds DDPM step k.
        self._alpha_bar = torch.cat(
            [torch.ones(1, dtype=torch.float64), self.scheduler.alphas_cumprod.double()]
        )

    def alpha_bar(self, t: torch.Tensor) -> torch.Tensor:
        t = torch.as_tensor(t).long()
        if t.min() < -1 or t.max() >= self.cfg.num_train_timesteps:
            raise ValueError(f"DDPM timesteps must lie in [-1, {self.cfg.num_train_timesteps - 1}]")
        return self._alpha_bar.to(t.device)[t + 1]

    def _coefficients(self, t: torch.Tensor, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        a = self.alpha_bar(t).to(like.device)
        return _expand(a.sqrt(), like), _expand((1.0 - a).sqrt(), like)

    def add_noise(self, x0, noise, t):
        signal, sigma = self._coefficients(t, x0)
        return signal * x0 + sigma * noise

    def velocity_target(self, x0, noise, t):
        signal, sigma = self._coefficients(t, x0)
        return signal * noise - sigma * x0

    def predict_clean(self, z, v, t):
        signal, sigma = self._coefficients(t, z)
        return signal * z - sigma * v

    def velocity_toward(self, z, x0, t):
        signal, sigma = self._coefficients(t, z)
        return (signal * z - x0) / sigma

    def predict_noise(self, z: torch.Tensor, v: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        signal, sigma = self._coefficients(t, z)
        return sigma * z + signal * v

    def step(self, z, v, t, t_prev):
        # DDIM (eta = 0): keep the implied noise, move the clean estimate to the lower noise level.
        x0 = self.predict_clean(z, v, t)
        eps = self.predict_noise(z, v, t)
        signal_prev, sigma_prev = self._coefficients(t_prev, z)
        return signal_prev * x0 + sigma_prev * eps

    def timesteps(self, steps=None):
        m = steps or self.cfg.deploy_steps
        self.scheduler.set_timesteps(m)
        return torch.cat([self.scheduler.timesteps.long().cpu(), torch.tensor([-1])])

    def sample_train_t(self, batch, generator=None):
        return torch.randint(0, self.cfg.num_train_timesteps, (batch,), generator=generator)


def build_schedule(cfg: ScheduleConfig) -> NoiseSchedule:
    if cfg.kind == "rectified_flow":
        return RectifiedFlowSchedule(cfg)
    if cfg.kind == "vpred_ddim":
        return VPredictionDDIMSchedule(cfg)
    raise ValueError(f"schedule.kind must be 'rectified_flow' or 'vpred_ddim', got {cfg.kind!r}")
