"""Planning, the first stage, before Ray starts: the spec, its limits, its trials with their validated
configs, the resources they need, the cost estimate and the protocol card.
"""
