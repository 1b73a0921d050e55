# hmepol — install, demo, tests, benchmarks, reproduction.
# TORCH_VERSION pins the CPU wheel; a GPU user picks their own build:
#   make install TORCH_SPEC="torch --index-url https://download.pytorch.org/whl/cu124"
PYTHON ?= python3
# The command, through the Python it was installed into (found without that Python's bin/ on PATH)
HMEPOL ?= $(PYTHON) -m hmepol_cli
TORCH_VERSION ?= 2.13.0
TORCH_SPEC ?= torch==$(TORCH_VERSION)
DEMO_DIR ?= outputs/demo
DEMO_FINETUNE ?= epochs=6 episodes=10 horizon=150 targets=1 config=0 fisher_fraction=0.25

.PHONY: install install-demo demo test test-fast bench lint results reproduce-quick reproduce-quick-slope reproduce-quick-multigrid reproduce chapter5 reproduce-corridor finetune-corridor finetune-continuation report-finetune-continuation studies report-wind-sweep clean

PIP_INSTALL = $(PYTHON) -m pip install --quiet

# What the demo needs: the package and its core dependencies (no tracking, MuJoCo or test
# packages, which make a cold install several times slower; tests/test_packaging.py checks it).
install-demo:
	$(PIP_INSTALL) "$(TORCH_SPEC)"
	$(PIP_INSTALL) -e .

# Everything the tests use: the extras too (CI runs this, then make test).
install:
	$(PIP_INSTALL) "$(TORCH_SPEC)"
	$(PIP_INSTALL) -e ".[dev,mujoco,tracking]"

# Trains Mepol and HMepol on a small slope world, fine-tunes both on a goal, and writes the report.
demo: install-demo
	$(HMEPOL) sweep experiment=demo algo=mepol,hmepol hydra.sweep.dir=$(DEMO_DIR)/pretrain
	$(HMEPOL) finetune init=$(DEMO_DIR)/pretrain/algo-hmepol_experiment-demo $(DEMO_FINETUNE) hydra.run.dir=$(DEMO_DIR)/finetune/hmepol
	$(HMEPOL) finetune init=$(DEMO_DIR)/pretrain/algo-mepol_experiment-demo $(DEMO_FINETUNE) hydra.run.dir=$(DEMO_DIR)/finetune/mepol
	$(HMEPOL) finetune init=none $(DEMO_FINETUNE) hydra.run.dir=$(DEMO_DIR)/finetune/scratch
	$(HMEPOL) report $(DEMO_DIR) --out $(DEMO_DIR)/report

# The tests run on every CPU (pytest-xdist; TEST_WORKERS=0 for one process): most are one
# single-threaded process each. Tests that read one expensive run share an xdist_group, so that
# run is made once, on one worker. logical, not auto: auto counts physical cores where psutil is
# installed, one on many 2-CPU machines.
TEST_WORKERS ?= logical
PYTEST = $(PYTHON) -m pytest -n $(TEST_WORKERS) --dist loadgroup

# Installs first, so `make test` also works on a fresh machine (a no-op when already installed).
test: install
	$(PYTEST)

# All but the tests marked slow (end-to-end runs of the command, the heaviest simulations).
test-fast: install
	$(PYTEST) -m "not slow"

bench:
	$(PYTHON) -m benchmarks.run
	$(PYTHON) -m benchmarks.population
	$(PYTHON) -m benchmarks.precision

lint:
	$(PYTHON) -m ruff check .

clean:
	rm -rf outputs/demo .pytest_cache .hypothesis

QUICK_DIR ?= outputs/quick
QUICK_SEEDS ?= seed=0,1,2,3

# Thesis 5.1 and 5.3 on a 2-core CPU, at the hyperparameters of tables A.1-A.3, with 40
# trajectories an epoch instead of 200 and 100 epochs instead of 500, 4 seeds each (populations),
# then the report. Measured: the slope half 2 h 32 min; multigrid alpha-Mepol 30 min, HMepol ~1.5 h
# (estimated from its first epochs). Interrupted, either half resumes from its checkpoints and
# skips what finished.
reproduce-quick: reproduce-quick-slope reproduce-quick-multigrid
	$(HMEPOL) report $(QUICK_DIR) --out $(QUICK_DIR)/report

reproduce-quick-slope:
	$(HMEPOL) sweep experiment=quick_slope algo=mepol,alphamepol,hmepol $(QUICK_SEEDS) progress=false hydra/launcher=population hydra.sweep.dir=$(QUICK_DIR)/slope

reproduce-quick-multigrid:
	$(HMEPOL) sweep experiment=quick_multigrid algo=alphamepol,hmepol $(QUICK_SEEDS) progress=false hydra/launcher=population hydra.sweep.dir=$(QUICK_DIR)/multigrid

# RESULTS.md's figures and tables, rebuilt from the runs kept in docs/results/ (about a minute):
# the chapter 5 runs, the collapse study, the float32 / bf16 curves and the
# decisive experiment: its pre-registered tables, rewritten in RESULTS.md between the
# "decisive tables" markers, and its curves per arm in docs/results/decisive/figures, interim
# while its runs go on (`hmepol report` skips unfinished runs, so it draws none of them yet).
results:
	$(HMEPOL) report docs/results/full docs/results/quick --out docs/results
	$(HMEPOL) report docs/results/collapse/n20-* --out docs/results/collapse/report-n20
	$(HMEPOL) report docs/results/collapse/n100-gradient docs/results/collapse/n100-exact docs/results/collapse/n100-adam docs/results/collapse/n100-bptt-full docs/results/collapse/n100-mepol --out docs/results/collapse/report-n100
	$(HMEPOL) report docs/results/collapse/finetune-epoch100 --out docs/results/collapse/report-finetune-epoch100
	$(HMEPOL) report docs/results/collapse/finetune-epoch75 --out docs/results/collapse/report-finetune-epoch75
	$(HMEPOL) report docs/results/precision --out docs/results/precision/report
	$(HMEPOL) report $(FINETUNE_OUT) --out $(FINETUNE_OUT)/report
	$(HMEPOL) study conf/study/decisive_corridor.yaml --status

# Chapter 5 at the thesis' full settings (tables A.1-A.3: 500 epochs, 8 seeds, 4 for multigrid) as
# populations over hyperparameters (hydra/launcher=population groups each sweep's runs by their
# program): slope Markov (Mepol + alpha-Mepol, 16 members) and HMepol (8); corridor Markov
# (Mepol + alpha-Mepol x 4 winds x 8 seeds, 64) and HMepol (4 winds x 8, 32); multigrid
# alpha-Mepol (4) and HMepol (4): six programs. DEVICE=cuda on a GPU, or
# LAUNCHER=population_slurm for one SLURM job per population; DRY=true prints the populations.
# Expected on a 2-core CPU (from `make bench`'s seconds per epoch, 30 off-policy iterations an
# epoch): ~26 days; the trust region stops many epochs early, so less (docs/reproducing.md).
FULL_DIR ?= outputs/full
DEVICE ?= cuda
LAUNCHER ?= population
DRY ?= false
SEEDS8 = seed=0,1,2,3,4,5,6,7
FULL = device=$(DEVICE) progress=false hydra/launcher=$(LAUNCHER) hydra.launcher.dry_run=$(DRY)
chapter5:
	$(HMEPOL) sweep experiment=slope_mepol,slope_alphamepol,slope_hmepol $(SEEDS8) $(FULL) hydra.sweep.dir=$(FULL_DIR)/slope
	$(HMEPOL) sweep experiment=corridor_mepol,corridor_alphamepol,corridor_hmepol wind=0.05,0.15,0.25,0.4 $(SEEDS8) $(FULL) hydra.sweep.dir=$(FULL_DIR)/corridor
	$(HMEPOL) sweep experiment=multigrid_alphamepol,multigrid_hmepol seed=0,1,2,3 $(FULL) hydra.sweep.dir=$(FULL_DIR)/multigrid
	if [ "$(DRY)" != true ]; then $(HMEPOL) report $(FULL_DIR) --out $(FULL_DIR)/report; fi

reproduce: chapter5 finetune-corridor

# What RESULTS.md's full-scale section ran: the corridor at wind 0.4 (~20 minutes of one H100).
reproduce-corridor:
	$(HMEPOL) sweep experiment=corridor_mepol,corridor_hmepol wind=0.4 $(SEEDS8) $(FULL) hydra.sweep.dir=$(FULL_DIR)/corridor

# Thesis Fig. 5.9 on a CPU: TRPO on five random targets of the counterclockwise corridor, from
# the wind-0.4 policies of seeds 0 and 1 of each algorithm, and from scratch.
FINETUNE ?= epochs=50 episodes=10 horizon=400 targets=5 config=1 fisher_fraction=0.25 progress=false
# The chapter 5 studies (docs/studies.md): where each stands (trains nothing), and the wind
# sweep's report with the decisive experiment's wind 0.4 beside it (Fig. 5.10, A.2);
# UNFINISHED=--unfinished draws it while runs are still going.
studies:
	for s in conf/study/*.yaml; do $(HMEPOL) study $$s --status || exit 1; echo; done
report-wind-sweep:
	$(HMEPOL) report docs/results/wind_sweep docs/results/decisive/mepol docs/results/decisive/exact $(UNFINISHED) --out docs/results/wind_sweep/report

# The pre-registered fine-tuning (docs/results/finetune_continuation/PREREGISTRATION.md): from
# the corridor continuation's final policies (seeds 8-11, and 12-15 when they exist), from a
# worktree of the pre-registration's commit.
CONTINUATION_DIR ?= docs/results/decisive
CONTINUATION_SEEDS ?= 8 9 10 11
FINETUNE_OUT ?= docs/results/finetune_continuation
FINETUNE_BOTH ?= epochs=50 episodes=10 horizon=400 targets=5 config=null fisher_fraction=0.25 progress=false threads=1
finetune-continuation:
	for s in $(CONTINUATION_SEEDS); do \
	  for a in mepol exact; do \
	    run=$$(ls -d $(CONTINUATION_DIR)/$$a/*_seed-$$s*/ | head -1); \
	    test -f "$$run/policy.pt" || { echo "no final policy in $$run"; exit 1; }; \
	    $(HMEPOL) finetune init=$$run seed=$$s $(FINETUNE_BOTH) output_dir=$(FINETUNE_OUT)/$$a-seed$$s || exit 1; \
	  done; \
	  $(HMEPOL) finetune init=none env=corridor wind=0.4 seed=$$s $(FINETUNE_BOTH) output_dir=$(FINETUNE_OUT)/scratch-seed$$s || exit 1; \
	done

# Its report: Fig. 5.9 per configuration and the pre-registered paired differences
# (finetune_differences.csv), over whatever runs exist so far.
report-finetune-continuation:
	$(HMEPOL) report $(FINETUNE_OUT) --out $(FINETUNE_OUT)/report

finetune-corridor:
	for s in 0 1; do \
	  for a in mepol hmepol; do \
	    $(HMEPOL) finetune init=$(FULL_DIR)/corridor/experiment-corridor_$${a}_seed-$${s}_wind-0.4 $(FINETUNE) output_dir=$(FULL_DIR)/finetune/$${a}-seed$${s} || exit 1; \
	  done; \
	  $(HMEPOL) finetune init=none env=corridor wind=0.4 seed=$$s $(FINETUNE) output_dir=$(FULL_DIR)/finetune/scratch-seed$$s || exit 1; \
	done
