"""The batched multi-robot policy server: frontend, engine and live scheduling loop."""
