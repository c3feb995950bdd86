"""The benchmarks behind ``cell bench``: numbers a user would want, failures counted first.

Each module measures one thing on the simulated cell or its parts and prints a report (or
JSON with ``cell --json``); none of them is a test. They may run the simulated devices, as the
import contracts allow, because they measure the product against a truth it does not share.
"""
