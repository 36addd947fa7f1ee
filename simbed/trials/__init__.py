"""Automated trials: the paper's experiments as suites of localization trials (``suites``), the gymnasium
environments (``envs``) and the agents that play them (``agents``)."""
