# The two README commands: `make demo` and `make test`. Each installs what it needs.
PYTHON ?= python3

.PHONY: install test demo reproduce lint format

install:
	@$(PYTHON) -c "import torch" 2>/dev/null || $(PYTHON) -m pip install torch==2.13.0
	$(PYTHON) -m pip install -q -e ".[test]"

test: install
	$(PYTHON) -m ruff check .
	$(PYTHON) -m ruff format --check .
	$(PYTHON) -m pytest -q

demo: install
	$(PYTHON) tools/demo.py

# every shipped model on all 13 variants of the 6-sequence val split -> docs/results/
VAL6 = data/synthetic_waymo_val6
reproduce: install
	$(PYTHON) tools/data/create_synthetic_waymo.py --out_dir $(VAL6) --train_sequences 12 \
		--train_frames 60 --val_sequences 6 --val_frames 198 --seed 0 --workers 2
	$(PYTHON) tools/reproduce.py --data_path $(VAL6) --out_dir docs/results --jobs 2

lint:
	$(PYTHON) -m ruff check . && $(PYTHON) -m ruff format --check .

format:
	$(PYTHON) -m ruff format . && $(PYTHON) -m ruff check --fix .
