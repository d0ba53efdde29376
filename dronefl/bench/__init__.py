"""Performance benchmarks (paper Table II, SPEC §9): ``dronefl bench --out DIR``.

Each module measures one part and returns typed figures (:mod:`~dronefl.bench.results`):

* :mod:`~dronefl.bench.simulator`: simulator speed;
* :mod:`~dronefl.bench.predictor`: predictor inference per drone step, training per epoch;
* :mod:`~dronefl.bench.vision`: rendered frames, the YOLO detector per frame;
* :mod:`~dronefl.bench.cloud`: EKF fusion and planner per step;
* :mod:`~dronefl.bench.closed_loop`: end-to-end Case 3 speed, DroneFL's communication;
* :mod:`~dronefl.bench.bandwidth`: communication per drone, DroneFL and centralized;
* :mod:`~dronefl.bench.energy`: RAPL readings or labelled estimates;
* :mod:`~dronefl.bench.results`: the figures, the goals and ``bench.json`` as types;
* goals, Table II and ``bench.md``: :mod:`dronefl.bench.report`;
* :mod:`~dronefl.bench.run`: :func:`~dronefl.bench.run.run_bench`, the whole benchmark;
* :mod:`~dronefl.bench.command`: the ``dronefl bench`` command.
"""
