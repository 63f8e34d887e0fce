"""viser's, mjviser's and websockets' internals, behind one door: no other module uses a private
name of theirs (tests/test_architecture.py); tests/test_viser_contract.py checks each against the
installed releases."""
