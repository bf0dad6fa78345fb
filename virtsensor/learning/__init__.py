"""The learning side: data sets from recordings, the trainer's recipes, evaluation (Table IV),
explanation (SHAP, figures) and scoring of a shipped model. Importing this package imports nothing heavy;
scikit-learn comes with the modules that fit models (the ``train`` extra)."""
