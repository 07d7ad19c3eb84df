"""The planner's parameters (the MPPI core's and its kernels'), built from the
configuration by name (common.config.by_name)."""

from __future__ import annotations

from dataclasses import dataclass

from common.config import Config, VehicleConfig, by_name
from services.planner import native
from services.planner.costs import CostParams
from services.planner.visibility import VisibilityParams
from services.plant.dynamics import ControlLimits


@dataclass(frozen=True)
class PlannerParams:
    """Named as their keys of `[planner]` (docs/parameters.md), the derived ones commented."""
    controller: str                    # deterministic | prescient | va
    samples: int                       # K (J in the paper)
    horizon: int                       # N
    dt_s: float
    substeps: int
    iterations: int
    temperature: float                 # lambda
    noise_std: tuple[float, float]     # derived: (noise_steer_rad, noise_force_n), delta, f_xt
    noise_correlation: float           # rho of the AR(1) noise along the horizon; 0 = white
    brake_samples: int                 # samples replaced by full braking (0: the paper's MPPI)
    swerve_samples: int                # ... and by full-lock swerves (0: the paper's MPPI)
    advance_samples: int               # ... and by the nominal done sooner (0: the paper's);
                                       # the three as many as K leaves room for
    effective_update: bool             # the update averages the force the vehicle felt (ours)
                                       # or the one commanded (False: the paper's)
    rollouts_published: int
    rollout_kernel: str                # jax | native: planner.rollout_kernel resolved
                                       # (services/planner/kernels.py)
    va_threads: int                    # native kernels' threads; 0 = this process's cores
    vehicle: VehicleConfig             # derived: [vehicle]
    limits: ControlLimits              # derived: from [vehicle]
    cost: CostParams                   # derived
    visibility: VisibilityParams       # derived

    @classmethod
    def from_config(cls, cfg: Config) -> PlannerParams:
        p = cfg.planner
        brake = min(p.brake_samples, p.samples - 1)
        swerve = min(p.swerve_samples, max(0, p.samples - 1 - brake))
        return by_name(cls, p, noise_std=(p.noise_steer_rad, p.noise_force_n),
                       brake_samples=brake, swerve_samples=swerve,
                       advance_samples=min(p.advance_samples,
                                           max(0, p.samples - 1 - brake - swerve)),
                       rollouts_published=min(p.rollouts_published, p.samples),
                       rollout_kernel=native.resolve(p.rollout_kernel),
                       vehicle=cfg.vehicle, limits=ControlLimits.from_config(cfg.vehicle),
                       cost=CostParams.from_config(cfg),
                       visibility=VisibilityParams.from_config(cfg))
