"""`aesplat view`: a prediction in the browser (viser; the optional ``viewer`` extra).

    aesplat view PREDICT_DIR | FILE.ply | --ckpt CKPT IMAGE IMAGE [...] [--host 127.0.0.1] [--port 8080]

See docs/view.md. The viewer listens on 127.0.0.1 unless ``--host`` says otherwise, prints its URL (which holds
a key drawn at each start: only that page may connect), and runs until Ctrl-C. It writes nothing: screenshots
go to the browser as downloads.
"""
