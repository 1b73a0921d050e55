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

test:
	$(PYTHON) -m pytest

bench:
	$(PYTHON) -m benchmarks.run

lint:
	$(PYTHON) -m ruff check hmepol_cli tests benchmarks

clean:
	rm -rf outputs/demo .pytest_cache .hypothesis
