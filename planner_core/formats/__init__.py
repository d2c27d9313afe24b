"""All of planner_core's I/O: scenario and trajectory JSON (`io`), the command line
(`cli`, `replan_cli`) and figures (`plot`, matplotlib imported only when drawing).

Nothing else in planner_core imports this package (except the public door,
`planner_core.api`, which re-exports the trajectory JSON codec); it imports the core.
"""
