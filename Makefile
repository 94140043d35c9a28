# The two commands a newcomer needs (see README):
#   make demo   install everything, then run the main job end to end on the embedded default data
#   make test   install everything, then run the test suite
PY := .venv/bin/python
DATA ?= data
export PYOPENGL_PLATFORM ?= egl
# torch's OpenMP threads sleep instead of spinning while they wait: 4-20x faster on shared CPUs.
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: setup demo train test bench clean

setup:
	@bash scripts/setup.sh

# generate the test split (+100 training images) -> infer with the reference models (RGB, ICP, oracle
# masks) -> evaluate -> a short training run of each network -> AR and training tables (~15 min)
demo: setup
	$(PY) -m cosy_lite.cli demo --data-root $(DATA)

# the full from-scratch job: generate the whole dataset -> train detector and refiner (demo profiles,
# ~26 min) -> infer -> evaluate (~42 min; outputs/train/)
train: setup
	$(PY) -m cosy_lite.cli demo --train --data-root $(DATA)

# two pytest workers (pytest-xdist), each test on one torch thread: both cores busy, the same arithmetic
# on any machine; long tests are rebalanced between the workers (worksteal)
TEST_WORKERS ?= 2
test: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist worksteal

bench: setup
	$(PY) bench/bench_synth.py

clean:
	rm -rf outputs .pytest_cache
