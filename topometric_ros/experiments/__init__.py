"""Research drivers, apart from the runtime path: the paper's noise sweep (evaluate), alarm calibration and
evaluation (alarms) and plane-detection quality (plane_quality). They may use the simulator and the product;
product modules never import them."""
