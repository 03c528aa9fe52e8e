"""The loose press: every chip its own elastic body, pressed between two rigid platens
with frictional contact by Incremental Potential Contact (ipctk).

:mod:`meshing.loose.model` declares the solve model and its keys (light, read at every
command-line start); :mod:`meshing.loose.press` runs the steps and writes the files;
:mod:`meshing.loose.ipc` is the solver, :mod:`meshing.loose.elements` the chips'
stiffness, :mod:`meshing.loose.material` their law at the press temperature and
:mod:`meshing.loose.bodies` the chips and platens from the mesh stage's model.
"""
