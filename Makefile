# Set-up is part of every target: the first run creates .venv (Python 3.12) and installs the
# project, its lerobot env plugin and the test tools; later runs reuse it.
VENV := .venv
STAMP := $(VENV)/.installed
PY := $(VENV)/bin/python

.PHONY: main test bench clean

$(STAMP): pyproject.toml plugins/lerobot_env_crowdnav/pyproject.toml policies/lerobot_policy_pdpo/pyproject.toml
	@test -x $(PY) || "$$(scripts/find_python312.sh)" -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]" -e plugins/lerobot_env_crowdnav -e policies/lerobot_policy_pdpo
	@touch $@

# The main job, on embedded defaults: the ORCA robot on the 500 test episodes of Bounded CrowdNav.
main: $(STAMP)
	$(VENV)/bin/lerobot-crowdnav-eval --policy.type=orca --env.task=BoundedCrowdNav-v0 \
		--eval.n_episodes=500 --eval.n_videos=1 --output_dir=outputs/main/orca_bounded --overwrite=true

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(VENV)/bin/lerobot-crowdnav-bench

clean:
	rm -rf $(VENV) outputs
