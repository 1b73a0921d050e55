import torch, time, sys, tempfile, pathlib
from benchmarks.run import thesis_config
from hmepol_cli.trainer import Trainer
from hmepol_cli import mepol, estimators
from hmepol_cli.rollout import collect, draw_configurations
torch.set_num_threads(2)
setups = {}
for prec in ("float32", "bf16"):
    t = Trainer(thesis_config("corridor", "hmepol", [f"precision={prec}"]), pathlib.Path(tempfile.mkdtemp())/"r")
    g = t.members[0].generator
    conf = draw_configurations(t.world, 100, 1, g)[None]
    r = collect(t.world, t.population, None, conf, 400, [g])
    nb = t.settings.estimator.search(estimators.particles_by_batch(r.particles[0], 1))
    sur = mepol.Surrogate(t.population, r, nb, torch.tensor([0]), t.settings)
    setups[prec] = (t, sur)
def it(prec):
    t, sur = setups[prec]
    e = sur(torch.arange(1)); mepol._gradients(e.objective, t.population.params)
best = {p: 1e9 for p in setups}
for rep in range(6):
    for p in setups:
        it(p); s=time.perf_counter(); it(p); best[p] = min(best[p], time.perf_counter()-s)
print({p: round(v,4) for p,v in best.items()}, "ratio", round(best["float32"]/best["bf16"],2))
