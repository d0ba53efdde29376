"""Results as types, a layer below everything that makes them (``experiments``, ``deploy``)
and everything that shows them (``report``): an episode's log and metrics
(:mod:`~dronefl.results.episode`), Table I's rows (:mod:`~dronefl.results.table1`) and the
offline FL results (:mod:`~dronefl.results.fl`), each serialised by :mod:`dronefl.serialize`."""
