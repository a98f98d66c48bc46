.PHONY: setup test lint quickstart bench

setup:
	bash scripts/setup.sh

test:
	bash scripts/test.sh

lint:
	ruff check src tests bench scripts
	mypy
	vulture src/mira scripts/vulture_allow.py --min-confidence 60

quickstart:
	bash scripts/quickstart.sh

bench:
	python bench/throughput.py
	python bench/results_page.py
