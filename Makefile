# hmepol — install, demo, tests, benchmarks, reproduction.
# TORCH_VERSION pins the CPU wheel; a GPU user picks their own build:
#   make install TORCH_SPEC="torch --index-url https://download.pytorch.org/whl/cu124"
PYTHON ?= python3
TORCH_VERSION ?= 2.13.0
TORCH_SPEC ?= torch==$(TORCH_VERSION)
DEMO_DIR ?= outputs/demo
DEMO_FINETUNE ?= epochs=6 episodes=10 horizon=150 targets=1 config=0 fisher_fraction=0.25

.PHONY: install demo test bench lint reproduce-quick reproduce clean

install:
	$(PYTHON) -m pip install --quiet "$(TORCH_SPEC)"
	$(PYTHON) -m pip install --quiet -e ".[dev]"

# Trains Mepol and HMepol on a small slope world, fine-tunes both on a goal, and writes the report.
demo: install
	hmepol sweep experiment=demo algo=mepol,hmepol hydra.sweep.dir=$(DEMO_DIR)/pretrain
	hmepol finetune init=$(DEMO_DIR)/pretrain/algo-hmepol_experiment-demo $(DEMO_FINETUNE) hydra.run.dir=$(DEMO_DIR)/finetune/hmepol
	hmepol finetune init=$(DEMO_DIR)/pretrain/algo-mepol_experiment-demo $(DEMO_FINETUNE) hydra.run.dir=$(DEMO_DIR)/finetune/mepol
	hmepol finetune init=none $(DEMO_FINETUNE) hydra.run.dir=$(DEMO_DIR)/finetune/scratch
	hmepol report $(DEMO_DIR) --out $(DEMO_DIR)/report

# Installs first, so `make test` also works on a fresh machine (a no-op when already installed).
test: install
	$(PYTHON) -m pytest

bench:
	$(PYTHON) -m benchmarks.run

lint:
	$(PYTHON) -m ruff check hmepol_cli tests benchmarks

clean:
	rm -rf outputs/demo .pytest_cache .hypothesis

QUICK_DIR ?= outputs/quick
FULL_DIR ?= outputs/full
QUICK_CORRIDOR = $(QUICK_DIR)/corridor/algo-$(1)_experiment-quick_corridor_seed-0_wind-0.4
QUICK_FINETUNE ?= epochs=15 episodes=10 horizon=400 targets=2 config=1 fisher_fraction=0.25

# About an hour on a 2-core CPU: every experiment of thesis ch. 5 at a reduced scale (plus HMepol
# with a tanh-bounded history encoder), then the report.
reproduce-quick:
	hmepol sweep experiment=quick_slope algo=mepol,alphamepol,hmepol seed=0,1 progress=false hydra.sweep.dir=$(QUICK_DIR)/slope
	hmepol sweep experiment=quick_corridor algo=mepol,hmepol wind=0.05,0.4 seed=0,1 progress=false hydra.sweep.dir=$(QUICK_DIR)/corridor
	hmepol sweep experiment=quick_multigrid algo=alphamepol,hmepol seed=0,1 progress=false hydra.sweep.dir=$(QUICK_DIR)/multigrid
	hmepol sweep experiment=quick_slope algo=hmepol policy.encoder_activation=tanh seed=0,1 progress=false hydra.sweep.dir=$(QUICK_DIR)/slope
	hmepol sweep experiment=quick_corridor algo=hmepol policy.encoder_activation=tanh wind=0.05,0.4 seed=0,1 progress=false hydra.sweep.dir=$(QUICK_DIR)/corridor
	hmepol sweep experiment=quick_multigrid algo=hmepol policy.encoder_activation=tanh seed=0,1 progress=false hydra.sweep.dir=$(QUICK_DIR)/multigrid
	hmepol finetune init=$(call QUICK_CORRIDOR,hmepol) $(QUICK_FINETUNE) progress=false hydra.run.dir=$(QUICK_DIR)/finetune/hmepol
	hmepol finetune init=$(call QUICK_CORRIDOR,mepol) $(QUICK_FINETUNE) progress=false hydra.run.dir=$(QUICK_DIR)/finetune/mepol
	hmepol report $(QUICK_DIR) --out $(QUICK_DIR)/report

# The thesis' full settings (tables A.1-A.3; 8 seeds, 4 for multigrid), meant for a cluster or a GPU:
#   make reproduce LAUNCHER=slurm
LAUNCHER ?= local
SEEDS8 = seed=0,1,2,3,4,5,6,7
reproduce:
	hmepol sweep hydra/launcher=$(LAUNCHER) experiment=slope_mepol,slope_alphamepol,slope_hmepol $(SEEDS8) progress=false hydra.sweep.dir=$(FULL_DIR)/slope
	hmepol sweep hydra/launcher=$(LAUNCHER) experiment=corridor_mepol,corridor_hmepol,corridor_alphamepol wind=0.05,0.15,0.25,0.4 $(SEEDS8) progress=false hydra.sweep.dir=$(FULL_DIR)/corridor
	hmepol sweep hydra/launcher=$(LAUNCHER) experiment=multigrid_alphamepol,multigrid_hmepol seed=0,1,2,3 progress=false hydra.sweep.dir=$(FULL_DIR)/multigrid
	hmepol report $(FULL_DIR) --out $(FULL_DIR)/report
