"""greedy_conditioned: after each pick, condition the policy on the picked camera (without its image) and
re-score the remaining candidates lazily."""
from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from b3dgs.acquisition import BatchSelector, Selection, camera_centres, check_radius, diverse_picks
from b3dgs.errors import B3dgsError


@dataclass
class GreedyConditioned(BatchSelector):
    """Pick the best score; ``policy.condition(ctx, pick)``; re-score and repeat. Re-scoring is lazy: every
    remaining candidate gets a value, ``score × policy.conditioned_ratio`` when the policy estimates what
    the conditioning did (native: from weight sums and posterior draws, no sampling render), else its last
    exact score (an upper bound, since conditioning on more views lowers a posterior's spread: Minoux's lazy
    greedy); the best value is re-scored exactly, and taken once its fresh score still beats every other
    value. At most ``max_rescore`` candidates are re-scored per pick (then the best fresh score is taken), so
    a pick costs one weight render (the conditioning), <= ``max_rescore`` candidate scorings and, once per
    batch, one point render per candidate for the ratio. Values are estimates, and Monte-Carlo noise can
    lift a conditioned score (native keys each candidate's draws to its position, so both scorings share it).

    A policy whose ``condition`` returns False (it has nothing a view without its image can update: proxy,
    ensemble, ppu, oracle, each saying why in ``no_conditioning``) is selected as ``batch=diverse`` with
    ``radius``, and the fallback and its reason are recorded in the selection's info."""

    max_rescore: int = 4  # candidates re-scored per pick at most (plus one weight render for the conditioning)
    radius: float = 1.0  # the diverse fallback's radius

    def validate(self, **kwargs):
        m = self.max_rescore
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise B3dgsError(f"acquisition batch greedy_conditioned: max_rescore={m!r} must be an integer >= 1",
                             "pass +acquisition.batch_settings.greedy_conditioned.max_rescore=4")
        check_radius(self.radius, "greedy_conditioned")

    def select(self, policy, ctx, candidates, budget):
        s0 = policy.score(ctx, candidates).detach().double().cpu()
        scores = [float(v) for v in s0]
        budget = min(int(budget), len(candidates))
        if budget == 0:
            return Selection([], scores, {"batch": "greedy_conditioned"})
        t0 = time.perf_counter()
        bound = s0.clone()  # the last exact score of each candidate
        first = int(torch.argmax(bound))  # the first maximum: top-k's first pick
        picks, rescored, cond_s = [first], [], 0.0
        try:
            tc = time.perf_counter()
            if budget > 1 and not policy.condition(ctx, candidates[first]):
                picks, h = diverse_picks(scores, camera_centres(candidates), camera_centres(ctx.train), budget,
                                         self.radius)
                return Selection(picks, scores, {"batch": "greedy_conditioned", "fallback": "diverse",
                                                 "reason": policy.no_conditioning, "radius": float(self.radius),
                                                 "spacing": h, "batch_time_s": time.perf_counter() - t0})
            cond_s += time.perf_counter() - tc
            while len(picks) < budget:
                rest = [j for j in range(len(candidates)) if j not in picks]
                ratio = policy.conditioned_ratio(ctx, candidates, rest)
                value = {j: float(s0[j] * ratio[k]) if ratio is not None else float(bound[j]) for k, j in enumerate(rest)}
                fresh: dict[int, float] = {}
                while True:
                    i = max(rest, key=lambda j: (fresh.get(j, value[j]), -j))  # ties: the first position
                    if i in fresh:
                        break
                    if len(fresh) >= int(self.max_rescore):
                        i = max(fresh, key=lambda j: (fresh[j], -j))
                        break
                    fresh[i] = bound[i] = float(policy.score_at(ctx, candidates, [i])[0])
                picks.append(i)
                rescored.append(len(fresh))
                if len(picks) < budget:
                    tc = time.perf_counter()
                    policy.condition(ctx, candidates[i])
                    cond_s += time.perf_counter() - tc
        finally:
            policy.reset_conditioning(ctx)
        return Selection(picks, scores, {"batch": "greedy_conditioned", "max_rescore": int(self.max_rescore),
                                         "rescored_per_pick": rescored, "conditioning_s": cond_s,
                                         "batch_time_s": time.perf_counter() - t0,
                                         "conditioned_scores": [float(bound[i]) for i in picks]})
