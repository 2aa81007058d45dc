from ftrain.torchrun import console

if __name__ == "__main__":
    console()
