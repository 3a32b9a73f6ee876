# Set-up is part of every target: the first run creates .venv (Python 3.12) and installs the
# project, its lerobot env plugin and the test tools; later runs reuse it.
VENV := .venv
STAMP := $(VENV)/.installed
PY := $(VENV)/bin/python

.PHONY: main test bench tables clean

$(STAMP): pyproject.toml plugins/lerobot_env_crowdnav/pyproject.toml policies/lerobot_policy_pdpo/pyproject.toml \
		policies/lerobot_policy_crowdnavpp/pyproject.toml
	@test -x $(PY) || "$$(scripts/find_python312.sh)" -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]" -e plugins/lerobot_env_crowdnav -e policies/lerobot_policy_pdpo \
		-e policies/lerobot_policy_crowdnavpp
	@touch $@

# The main job on embedded defaults (7.5-15 min on one CPU core, README): the policies shipped in
# models/lerobot-crowdnav and the baselines on the 500 test seeds -> outputs/main/report.md.
# MAIN_ARGS passes flags, e.g. MAIN_ARGS=--config_path=configs/main/retrain.yaml trains them all
# from scratch (demonstrations -> lerobot-train -> diffusion PPO; rerunning resumes).
main: $(STAMP)
	$(VENV)/bin/lerobot-crowdnav-main $(MAIN_ARGS)

# The results and baseline tables of README.md, docs/results.md and docs/simulator.md, rewritten from docs/data/ (the
# CSV tables of make main's report and of lerobot-crowdnav-baselines). TABLES_ARGS refreshes
# docs/data/ from runs first: TABLES_ARGS="--main=outputs/main --baselines=outputs/baselines".
tables: $(STAMP)
	$(PY) -m lerobot_crowdnav.evaluation.tables $(TABLES_ARGS)

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(VENV)/bin/lerobot-crowdnav-bench

clean:
	rm -rf $(VENV) outputs
