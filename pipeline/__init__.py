"""Pipeline: command line, scenario files, run directory and the wiring of the stages."""
