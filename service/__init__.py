"""The joint-limit constitution service: numerical core (`jointlimits.service.core`) and its HTTP shell."""
