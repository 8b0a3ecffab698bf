"""The joint-limit constitution service: numerical core (`service.core`) and its HTTP shell."""
