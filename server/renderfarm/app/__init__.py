"""The job service (FarmService) and what it is made of: job operations, worker sessions, the
database write-behind, checkpoints, convergence history, callers. Imports domain and infra,
never api or cli."""
