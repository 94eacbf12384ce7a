"""Two models of one's own, shipped with the package so that they load by module name from any
folder (`xvoe score --model xvoe.examples.frame_change:FrameChange`): what the benchmark asks of
a model, in a screen each (docs/evaluate-your-model.md). They use the public API alone."""
