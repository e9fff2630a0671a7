"""The wiring layer: the `wsnav` command line, site pictures, and (later) the demo and experiment harness.

Only this layer may import several components at once; the components meet at the message contract.
"""
