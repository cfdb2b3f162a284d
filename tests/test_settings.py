import pytest
from pydantic import Field

from esiaf.settings import ComponentSettings, SettingsError, load_settings, unknown_variables


class DemoSettings(ComponentSettings):
    threshold_db: float = 65.0
    topics: list[str] = Field(default_factory=lambda: ["a"])


def test_defaults_then_yaml_then_environment(tmp_path):
    config = tmp_path / "demo.yaml"
    config.write_text("threshold_db: 70\nstream_id: from-yaml\n")
    env = {"ESIAF_DEMO_THRESHOLD_DB": "72", "ESIAF_DEMO_TOPICS": "[x, y]"}
    settings = load_settings(DemoSettings, "demo", config=config, env=env)
    assert settings.threshold_db == 72.0
    assert settings.stream_id == "from-yaml"
    assert settings.topics == ["x", "y"]
    assert settings.name == "demo"


def test_common_settings_for_all_services_and_the_specific_one_wins():
    env = {"ESIAF_ORCHESTRATOR_URL": "http://robot:8000", "ESIAF_STREAM_ID": "all",
           "ESIAF_DEMO_STREAM_ID": "mine"}
    settings = load_settings(DemoSettings, "demo", env=env)
    assert settings.orchestrator_url == "http://robot:8000"
    assert settings.stream_id == "mine"


def test_config_file_from_environment(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text("threshold_db: 1\n")
    assert load_settings(DemoSettings, "demo", env={"ESIAF_DEMO_CONFIG": str(config)}).threshold_db == 1


@pytest.mark.parametrize("env, message", [
    ({"ESIAF_DEMO_TRESHOLD_DB": "1"}, "unknown setting ESIAF_DEMO_TRESHOLD_DB"),
    ({"ESIAF_DEMO_THRESHOLD_DB": "loud"}, "threshold_db"),
    ({"ESIAF_DEMO_LOG_LEVEL": "verbose"}, "unknown log level 'verbose'"),
])
def test_bad_environment_is_a_clear_error(env, message):
    with pytest.raises(SettingsError, match=message):
        load_settings(DemoSettings, "demo", env=env)


def test_unknown_yaml_key_and_bad_yaml_are_errors(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text("treshold_db: 1\n")
    with pytest.raises(SettingsError, match="treshold_db"):
        load_settings(DemoSettings, "demo", config=config, env={})
    config.write_text("a: [\n")
    with pytest.raises(SettingsError, match="not valid YAML"):
        load_settings(DemoSettings, "demo", config=config, env={})
    with pytest.raises(SettingsError, match="cannot read config file"):
        load_settings(DemoSettings, "demo", config=tmp_path / "missing.yaml", env={})


def test_a_bad_value_names_the_source_it_came_from(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text("threshold_db: loud\n")
    env = {"ESIAF_DEMO_STREAM_ID": "s", "ESIAF_DEMO_TOPICS": "[x]"}
    with pytest.raises(SettingsError, match=r"^bad demo settings \(from command line\): threshold_db"):
        load_settings(DemoSettings, "demo", env=env, threshold_db="loud")
    with pytest.raises(SettingsError, match=rf"\(from config file {config}\): threshold_db"):
        load_settings(DemoSettings, "demo", config=config, env=env)
    with pytest.raises(SettingsError, match=r"\(from environment\): threshold_db"):
        load_settings(DemoSettings, "demo", config=config, env={**env, "ESIAF_DEMO_THRESHOLD_DB": "loud"})
    # a good value given later wins, and the bad one overridden is not blamed
    assert load_settings(DemoSettings, "demo", config=config, env=env, threshold_db=3).threshold_db == 3
    with pytest.raises(SettingsError, match=r"\(from environment and command line\): threshold_db.*; topics"):
        load_settings(DemoSettings, "demo", env={"ESIAF_DEMO_THRESHOLD_DB": "loud"}, topics=5)


def test_a_bad_set_on_the_command_line_is_blamed_on_the_command_line():
    import subprocess
    import sys

    from esiaf.tools.testing import REPO
    result = subprocess.run([sys.executable, "-m", "esiaf_services.vad", "--set", "energy.db_min=loud"], cwd=REPO,
                            capture_output=True, text=True, timeout=60,
                            env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO), "ESIAF_STREAM_ID": "s"})
    assert result.returncode == 2
    assert result.stderr.startswith("vad: bad vad settings (from command line): energy.db_min:"), result.stderr


def test_a_component_without_a_docstring_still_starts_its_command_line(capsys):
    from esiaf.component import Component
    from esiaf.runner import main

    class Bare(Component):
        service = "bare"

    Bare.__doc__ = None
    with pytest.raises(SystemExit) as exited:
        main(Bare, ["--help"])
    assert exited.value.code == 0
    out = capsys.readouterr().out
    assert "the bare component" in out
    # every setting is listed, the common ones too, with its environment variable
    assert "log_level = 'INFO'  (ESIAF_BARE_LOG_LEVEL or ESIAF_LOG_LEVEL)" in out
    assert "orchestrator_url" in out


def test_a_bad_log_level_is_one_line_and_exit_2(capsys):
    from esiaf.component import Component
    from esiaf.runner import main

    class Quiet(Component):
        """Does nothing."""
        service = "quiet"

    assert main(Quiet, ["--set", "log_level=verbose"]) == 2
    err = capsys.readouterr().err
    assert "unknown log level 'verbose'" in err and "Traceback" not in err


def test_variables_that_name_no_service_are_found():
    from esiaf.services import known_services
    env = {"ESIAF_VDA_DB_MIN": "3", "ESIAF_VAD_DB_MIN": "3", "ESIAF_STREAM_ID": "s", "ESIAF_TOKEN": "t",
           "ESIAF_ORCHESTRATOR_URL": "u", "ESIAF_GRABBER_REPLICAS": "1", "ESIAF_RATE_WINDOW": "2", "HOME": "/"}
    services = known_services()
    assert {"vad", "asr", "orchestrator", "voiceid"} <= services
    assert unknown_variables(env, services) == ["ESIAF_RATE_WINDOW", "ESIAF_VDA_DB_MIN"]
    assert unknown_variables(env, services | {"rate"}) == ["ESIAF_VDA_DB_MIN"]  # a plug-in's own


def test_a_service_started_with_a_misspelt_variable_says_so(tmp_path):
    import os
    import subprocess
    import sys

    from esiaf.tools.testing import REPO
    env = {**os.environ, "PYTHONPATH": str(REPO), "ESIAF_VDA_DB_MIN": "3", "ESIAF_ORCHESTRATOR_URL": "http://127.0.0.1:9",
           "ESIAF_REGISTER_TIMEOUT_S": "0.5", "ESIAF_VAD_BACKEND": "energy"}
    done = subprocess.run([sys.executable, "-m", "esiaf_services.vad"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 2  # no orchestrator: it gives up, but said first what it ignored
    assert "WARNING vad [vad] ESIAF_VDA_DB_MIN names no service" in done.stderr, done.stderr


@pytest.mark.parametrize("source", ["yaml", "environment", "command line"])
def test_an_old_spelling_works_for_one_release_with_one_deprecation_line(tmp_path, caplog, source):
    from esiaf_services.asr.service import AsrSettings
    config = tmp_path / "asr.yaml"
    config.write_text("nbest: 3\n" if source == "yaml" else "{}\n")
    settings = load_settings(AsrSettings, "asr", config=config,
                             env={"ESIAF_ASR_NBEST": "3"} if source == "environment" else {},
                             **({"nbest": 3} if source == "command line" else {}))
    assert settings.n_best == 3 and settings.hypotheses() == 3
    [line] = [r.getMessage() for r in caplog.records if "deprecated" in r.getMessage()]
    assert line == "setting nbest is deprecated and goes in the next release: it is now n_best"


def test_the_new_spelling_wins_and_each_backend_keeps_its_default(caplog):
    from esiaf_services.asr.service import AsrSettings
    assert load_settings(AsrSettings, "asr", env={"ESIAF_ASR_N_BEST": "2"}, nbest=7).n_best == 2
    assert "(both given: n_best=2 wins)" in caplog.text
    assert load_settings(AsrSettings, "asr", env={}).hypotheses() == 5
    assert load_settings(AsrSettings, "asr", env={}, backend="whisper").hypotheses() == 10
    with pytest.raises(SettingsError, match="n_best"):
        load_settings(AsrSettings, "asr", env={"ESIAF_ASR_N_BEST": "0"})


@pytest.mark.parametrize("source", ["yaml", "environment", "command line"])
def test_a_backends_settings_are_nested_under_its_name(tmp_path, source):
    from esiaf_services.vad.service import VadSettings
    config = tmp_path / "vad.yaml"
    config.write_text("backend: energy\n" + ("energy: {db_min: 71}\n" if source == "yaml" else ""))
    settings = load_settings(VadSettings, "vad", config=config,
                             env={"ESIAF_VAD_ENERGY__DB_MIN": "71"} if source == "environment" else {},
                             **({"energy": {"db_min": 71}} if source == "command line" else {}))
    assert settings.energy.db_min == 71 and settings.energy.keep_alive_ms == 400  # the rest: defaults
    assert settings.silero.threshold == 0.5


def test_nested_settings_from_several_sources_merge_key_by_key(tmp_path):
    from esiaf_services.vad.service import VadSettings
    config = tmp_path / "vad.yaml"
    config.write_text("backend: energy\nenergy: {db_min: 71, keep_alive_ms: 300}\n")
    settings = load_settings(VadSettings, "vad", config=config, env={"ESIAF_VAD_ENERGY__DB_MIN": "72"})
    assert (settings.energy.db_min, settings.energy.keep_alive_ms) == (72, 300)


def test_another_backends_settings_are_refused_with_where_they_came_from():
    from esiaf_services.vad.service import VadSettings
    with pytest.raises(SettingsError, match=r"^bad vad settings \(from environment\): energy.db_min is for another "
                       r"backend than 'silero' \(set backend, or leave it out\)$"):
        load_settings(VadSettings, "vad", env={"ESIAF_VAD_ENERGY__DB_MIN": "70"})
    with pytest.raises(SettingsError, match=r"\(from command line\): whisper.beam_size, whisper.model_dir are for"):
        from esiaf_services.asr.service import AsrSettings
        load_settings(AsrSettings, "asr", env={}, whisper={"model_dir": "/m", "beam_size": 2})
    with pytest.raises(SettingsError, match=r"backend: Value error, unknown backend 'webrtc'; one of silero, energy"):
        load_settings(VadSettings, "vad", env={"ESIAF_VAD_BACKEND": "webrtc"})


def test_an_unknown_nested_variable_lists_the_current_names_only():
    from esiaf_services.vad.service import VadSettings
    with pytest.raises(SettingsError, match="unknown setting ESIAF_VAD_ENERGY__DB_MAX") as error:
        load_settings(VadSettings, "vad", env={"ESIAF_VAD_ENERGY__DB_MAX": "70"})
    assert "ESIAF_VAD_ENERGY__DB_MIN" in str(error.value) and "ESIAF_VAD_DB_MIN" not in str(error.value)


def test_a_flat_old_name_reaches_its_backend_with_one_deprecation_line(caplog):
    from esiaf_services.vad.service import VadSettings
    settings = load_settings(VadSettings, "vad", env={"ESIAF_VAD_DB_MIN": "70", "ESIAF_VAD_BACKEND": "energy"})
    assert settings.energy.db_min == 70
    [line] = [r.getMessage() for r in caplog.records if "deprecated" in r.getMessage()]
    assert line == "setting db_min is deprecated and goes in the next release: it is now energy.db_min"
    with pytest.raises(SettingsError, match=r"\(from environment\): energy.db_min is for another backend"):
        load_settings(VadSettings, "vad", env={"ESIAF_VAD_DB_MIN": "70"})


def test_help_lists_each_backends_settings_apart():
    import subprocess
    import sys

    from esiaf.tools.testing import REPO
    done = subprocess.run([sys.executable, "-m", "esiaf_services.asr", "--help"], cwd=REPO, capture_output=True,
                          text=True, timeout=60)
    head, _, backends = done.stdout.partition("settings of the pocketsphinx backend")
    assert "  grammar = ''  (ESIAF_ASR_GRAMMAR)" in head and "beam_size" not in head
    assert "whisper.beam_size = 5  (ESIAF_ASR_WHISPER__BEAM_SIZE)" in backends
    assert "pocketsphinx.language_weight = 7.5  (ESIAF_ASR_POCKETSPHINX__LANGUAGE_WEIGHT)" in backends
