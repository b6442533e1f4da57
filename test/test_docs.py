"""The generated pages of docs/ are what the code generates: they cannot drift from it unnoticed."""

from ddarm.cli.docs import PAGE, cli_reference


def test_docs_cli_md_is_the_argument_parser_as_it_is():
    assert PAGE.read_text() == cli_reference(), 'docs/cli.md is out of date: run make docs'


def test_every_command_and_option_of_the_parser_is_on_the_page():
    from ddarm.cli.docs import _commands
    from ddarm.cli.main import build_parser

    page = PAGE.read_text()
    for name, (_, command) in _commands(build_parser()).items():
        assert f'## ddarm {name}\n' in page
        for action in command._actions:
            for flag in action.option_strings:
                if flag not in ('-h', '--help'):
                    assert f'`{flag}' in page, (name, flag)


def test_docs_ros_interface_md_is_the_nodes_as_they_declare_themselves():
    from ddarm.cli.docs import ROS_PAGE, ros_interface

    assert ROS_PAGE.read_text() == ros_interface(), 'docs/ros-interface.md is out of date: run make docs'


def test_the_episode_options_table_of_the_model_specification_is_the_episodes_defaults():
    from ddarm.cli.docs import EPISODE_OPTIONS, SPEC_PAGE, specification_page
    from ddarm.episodes.spec import EPISODE_DEFAULTS, EpisodeSpec

    assert SPEC_PAGE.read_text() == specification_page(), 'docs/model-specification.md §14 is out of date: run make docs'
    # Every field of the episode is on it (kv on kp's row, coulomb_friction on viscous_friction's, mjcf_joints on
    # mjcf's), its default EPISODE_DEFAULTS'.
    named = {field for field, _, _ in EPISODE_OPTIONS}
    assert named == set(EpisodeSpec.__dataclass_fields__) - {'kv', 'coulomb_friction', 'mjcf_joints'}
    assert EPISODE_DEFAULTS['delay'] == 1 and '| delay d | 1 |' in SPEC_PAGE.read_text()
