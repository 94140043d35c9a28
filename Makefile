# The two commands a newcomer needs (see README):
#   make demo   install everything, then run the main job end to end on the embedded default data
#   make test   install everything, then run the test suite
PY := .venv/bin/python
DATA ?= data
export PYOPENGL_PLATFORM ?= egl
# torch's OpenMP threads sleep instead of spinning while they wait: 4-20x faster on shared CPUs.
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: setup demo test bench clean

setup:
	@bash scripts/setup.sh

# generate -> train detector, coarse, refiner (demo profiles) -> infer (RGB, ICP, oracle boxes) -> eval
demo: setup
	$(PY) -m cosy_lite.cli generate --out $(DATA)/ycbvsynth --workers 2
	$(PY) -m cosy_lite.cli show $(DATA)/ycbvsynth --split test --scene 0 --image 0 --out outputs/demo_show_test_000000_000000.png
	$(PY) -m cosy_lite.cli contact-sheet $(DATA)/ycbvsynth --split train_pbr -n 16 --out outputs/demo_contact_sheet.png
	$(PY) -m cosy_lite.cli demo --data-root $(DATA)

test: setup
	$(PY) -m pytest -q

bench: setup
	$(PY) bench/bench_synth.py

clean:
	rm -rf outputs .pytest_cache
