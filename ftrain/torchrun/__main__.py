from ftrain.torchrun import console

console()
