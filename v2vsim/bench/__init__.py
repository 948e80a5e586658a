"""`v2vsim bench WHAT`: one module per benchmark (sensors, models, comm, run, env, placement), each with
`main(argv) -> int`. Speed is measured here, never in tests."""
