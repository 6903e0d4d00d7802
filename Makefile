# The three commands of the README: set-up, tests, demo.
.PHONY: setup test demo bench
setup:
	./scripts/setup.sh
test:
	./scripts/run_tests.sh
demo:
	.venv/bin/vlm-vpr demo --out demo_out
bench:
	.venv/bin/python benchmarks/bench_core.py
