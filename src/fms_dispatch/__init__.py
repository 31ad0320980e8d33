"""fms_dispatch: dispatching rules, metaheuristic, exact CP-SAT model, RL agent and lookahead."""
