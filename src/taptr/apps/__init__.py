"""What people build on the tracker.

Video editing by a tracked region (`editing`), the interactive demo (`demo`), the speed
benchmark (`benchmark`) and the attention analysis (`attention_analysis`).
"""
