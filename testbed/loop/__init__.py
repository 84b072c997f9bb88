"""The control loop's core, shared by the simulators and the nodes: the flow map phi_T
(``flow``, ``_dop853``), ZOH and LQR (``control``), Algorithms 1 and 2 (``quantizer``), the
loop's parameter types and codebook (``params``), the state machines (``protocol``), the
network channel model (``channel``), the plant's sensor, actuator and disturbance (``device``,
``distributions``) and the plant contract (``plantcheck``)."""
