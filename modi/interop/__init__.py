"""Reading what the authors' released code wrote (MoDi, its encoder, GANimator) into modi runs.

Each released format has its own module; nothing here imports the released sources: a user who holds a
checkpoint does not need the authors' code to convert it.
"""
