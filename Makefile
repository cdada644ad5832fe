# The two commands of the README. Both set everything up first (scripts/setup.sh is idempotent).
.PHONY: setup demo test bench

setup:
	@bash scripts/setup.sh

demo: setup
	.venv/bin/dp5k demo demo-out

test: setup
	.venv/bin/python -m pytest -q -p no:cacheprovider --timeout=900 -n auto --maxprocesses 4 --dist worksteal --durations=20

bench: setup
	.venv/bin/python benchmarks/run_all.py
