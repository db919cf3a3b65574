"""A stand-in for PC-NBV's ``dataset`` package, which MA-SCVP's copy of PC-NBV imports but does not ship."""
