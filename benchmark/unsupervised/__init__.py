"""Thesis chapters 4-5: learning depth without ground truth: the reprojection losses
(reprojection), the toy study (toy*), frame sequences and the photometric training step
(sequences, rotation, training: registered in benchmark.engine.steps), fine-tuning on footage
(footage_sequences, finetune) and the sequence scoring of Tables 5.2-5.3 (sequence_eval,
sequence_report)."""
