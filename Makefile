# MMM: every target runs inside the project's virtual environment (.venv), created by `make setup`.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# The CPU build of torch 2.13.0 on the project machines; on a GPU machine the same pin pulls the
# CUDA build from the registry.
TORCH_VERSION ?= 2.13.0
STAMP := $(VENV)/.installed
DATA ?= data/synthetic
ARGS ?=

.DEFAULT_GOAL := help
.PHONY: help setup test data demo train-stage1 train-stage2 train-length tokenize bench-train bench-generate bench evaluate train-evaluator pipeline promote models mlflow-ui clean

help: ## list the targets
	@grep -E '^[a-zA-Z0-9_%-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-16s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "torch==$(TORCH_VERSION)"
	$(BIN)/python -m pip install -q -e ".[dev,text]"
	touch $(STAMP)

setup: $(STAMP) ## create .venv and install the package (idempotent)

test: $(STAMP) ## run the test suite (sets up first when needed)
	$(BIN)/python -m pytest -q

$(DATA)/all.txt: | $(STAMP)
	$(BIN)/mmm data synth --out $(DATA) $(ARGS)

data: $(DATA)/all.txt ## generate the synthetic default dataset into $(DATA) (once; `make clean` removes it)

DEMO_PROMPTS := "a person walks forward slowly" "someone jumps twice" "a person waves with the right hand" "the person squats down two times"

demo: $(DATA)/all.txt ## the main job on the embedded default: data, both stages (tiny), length estimator, generated clips in outputs/demo
	$(BIN)/mmm data preview $(DATA) --out outputs/demo/dataset --count 12
	$(BIN)/mmm train stage1 trainer.enable_progress_bar=false
	$(BIN)/mmm train stage2 trainer.enable_progress_bar=false
	$(BIN)/mmm train length trainer.enable_progress_bar=false
	@i=0; for prompt in $(DEMO_PROMPTS); do \
		$(BIN)/mmm generate --text "$$prompt" --num-samples 2 --seed 0 --overwrite --out outputs/demo/generated/$$i || exit 1; i=$$((i+1)); \
	done
	@echo "Look at: outputs/demo/dataset/contact_sheet.png, outputs/demo/generated/*/*/motion.gif, and the runs in the MLflow dashboard (make mlflow-ui)"

train-stage1: $(STAMP) ## train the tokenizer (tiny size on the synthetic data by default); ARGS="key=value ..."
	$(BIN)/mmm train stage1 $(ARGS)

train-stage2: $(STAMP) ## train the masked transformer on the newest stage-1 result (or ARGS="stage1=RUN_ID|PATH|models:/NAME@ALIAS ...")
	$(BIN)/mmm train stage2 $(ARGS)

train-length: $(STAMP) ## train the length estimator used when no length is given (ARGS as for train-stage2)
	$(BIN)/mmm train length $(ARGS)

tokenize: $(STAMP) ## tokenize the dataset with a stage-1 model and cache caption embeddings (ARGS as for train-stage2)
	$(BIN)/mmm tokenize $(ARGS)

bench-train: $(STAMP) ## training speed and peak memory of both stages (outputs/bench/train_speed.json)
	$(BIN)/python benchmarks/train_speed.py $(ARGS)

bench-generate: $(STAMP) ## time per sentence against length, AITS and a 10.9-minute motion (outputs/bench/generation_speed.json)
	$(BIN)/python benchmarks/generation_speed.py $(ARGS)

bench: bench-train bench-generate ## all speed measurements (training and generation), JSON and plots in outputs/bench/

train-evaluator: $(STAMP) ## train the own text-motion evaluator (contrastive), register it in MLflow
	$(BIN)/mmm train evaluator $(ARGS)

evaluate: $(STAMP) ## the protocol (20 replications), reconstruction metrics and prompt adherence of the newest models (ARGS="key=value ...")
	$(BIN)/mmm evaluate $(ARGS)

ablate-%: $(STAMP) ## an ablation table as a sweep: ablate-reset|cross-layers|schedule|temperature|topk|topp (Tables 8-13)
	$(BIN)/mmm ablate $* $(ARGS)

pipeline: $(STAMP) ## the full pipeline (evaluator, stage 1, promote, tokenize, stage 2, evaluate, promote) as one MLflow run; unchanged steps are skipped
	$(BIN)/mmm pipeline full $(ARGS)

promote: $(STAMP) ## measure and register the newest evaluator, tokenizer and text-to-motion runs; champion moves only when they win
	$(BIN)/mmm pipeline promote $(ARGS)

models: $(STAMP) ## registered models: versions, aliases, metrics
	$(BIN)/mmm models list

mlflow-ui: $(STAMP) ## serve the MLflow dashboard for this project's store on http://127.0.0.1:5000
	$(BIN)/mlflow server --backend-store-uri sqlite:///$(CURDIR)/mlflow.db --default-artifact-root $(CURDIR)/mlartifacts --host 127.0.0.1 --port 5000

clean: ## remove generated data and outputs (keeps .venv and the MLflow store)
	rm -rf data outputs
