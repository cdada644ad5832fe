# The two commands of the README. Both set everything up first (scripts/setup.sh is idempotent): the demo what it
# needs, the tests their tools too. Choose the PyTorch build with TORCH_INDEX_URL / TORCH_SPEC and the interpreter
# with PYTHON, in the environment or here: make setup TORCH_INDEX_URL=https://download.pytorch.org/whl/cu128
.PHONY: setup setup-tests demo test bench
export PYTHON TORCH_SPEC TORCH_INDEX_URL

setup:
	@bash scripts/setup.sh

setup-tests:
	@bash scripts/setup.sh --with-tests

demo: setup
	.venv/bin/dp5k demo --out demo-out

test: setup-tests
	.venv/bin/python -m pytest -q -p no:cacheprovider --timeout=900 -n auto --maxprocesses 4 --dist worksteal --durations=20

bench: setup
	.venv/bin/python benchmarks/run_all.py
