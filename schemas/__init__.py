"""The wsnav message contract and site file: the one vocabulary every component shares.

Depends on nothing else of ours, so firmware tooling, broker, robot agent and zone simulator can all import it.
"""
