"""The render daemon: assemble steps, repartition, acceleration structure, ray tracing."""
