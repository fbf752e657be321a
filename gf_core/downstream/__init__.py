"""What users do with a reconstruction: continue it with a simulator (``predict``), edit it first
(``edit``), or export it for other tools (``export``)."""
