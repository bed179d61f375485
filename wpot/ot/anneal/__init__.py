"""The paper's annealing (Algorithm 1): at each inverse temperature beta the saddle point (lambda, mu) of the
free energy is found by Newton's method, then beta grows until U = sum G C converges.

- `wpot.ot.anneal.schedule`: the beta schedule, a pure function;
- `wpot.ot.anneal.state`: the records shared by the engine and its loops (`Point`, `DualSums`, `DualSnapshot`,
  `Timers`);
- `wpot.ot.anneal.newton`: the Newton engine (`Engine`): state, evaluations, Newton's method and its step API;
- `wpot.ot.anneal.schur`: the interface of its two Newton loops (`NewtonSolver`) and the Schur-complement
  kernels they share; `wpot.ot.anneal.host`: the host loop (`HostSolver`: CG or a direct solve on the host,
  SuperLU preconditioner); `wpot.ot.anneal.resident`: the device-resident loop (`DeviceSolver`: CG, FSAI
  preconditioner and line search as kernels);
- `wpot.ot.anneal.linear`, `wpot.ot.anneal.multilevel`: the host linear solvers and the multilevel V-cycle;
- `wpot.ot.anneal.loop`: the annealing loop over beta (`anneal`);
- `wpot.ot.anneal.ipm`: the interior-point start (``method="ipm"``);
- `wpot.ot.anneal.balanced`, `wpot.ot.anneal.partial`: balanced (Eq. 6-16) and partial (Eq. 17-26) solves.
"""
